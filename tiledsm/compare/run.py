"""The runner of ``pipeline: compare``: the comparison of the recipe's two
DSMs into the run folder (:func:`tiledsm.compare.compare_dsms`), called by
:func:`tiledsm.pipelines.run_recipe` under the folder's lock. It writes
``dh.zarr``, ``dh.tif``, the figures, ``report.html`` and ``metrics.json``
(the plan's warnings included); ``run_recipe`` adds ``run.log`` and
``recipe.resolved.yaml``."""

from __future__ import annotations

from pathlib import Path

__all__ = ["run_compare"]


def run_compare(recipe, out: Path, cluster=None, overwrite: bool = False, plan=None) -> dict:
    """Compare ``recipe.input.other`` with ``recipe.input.ref`` into ``out``;
    returns the metrics (those of ``metrics.json``).

    The products are staged in a hidden temporary folder and moved into
    place when all succeeded (:func:`~tiledsm.compare.compare_dsms`): a
    killed run leaves the folder's earlier products, and its staging is
    swept by the next run that takes the folder's lock. ``overwrite`` is
    the plan's business (an earlier run of another recipe)."""
    from tiledsm.cluster import compute_context
    from tiledsm.compare.stage import compare_dsms

    warnings = list(plan.warnings) if plan is not None else []
    with compute_context(cluster or recipe.cluster.config()):
        result = compare_dsms(recipe.input.ref, recipe.input.other, out, recipe.compare, recipe.output,
                              warnings=warnings)
    return result.metrics
