"""The runner of ``pipeline: sr``: the plan's lazy super-resolved image
computed into the run folder, called by :func:`tiledsm.pipelines.run_recipe`
under the folder's lock.

``sr.tif`` (GeoTIFF, float32, NaN nodata, the RPC of the input scaled,
``sr_*`` tags) or ``sr.zarr`` is written atomically (:func:`tiledsm.io.atomic_path`):
a killed run leaves only a hidden temporary, swept by the next run that
takes the folder's lock, which then writes the same bytes again.
``metrics.json`` (the plan's warnings included) follows the product;
``run_recipe`` adds ``run.log`` and ``recipe.resolved.yaml``.
"""

from __future__ import annotations

import time
from pathlib import Path

__all__ = ["run_sr"]


def run_sr(recipe, out: Path, cluster=None, overwrite: bool = False, plan=None) -> dict:
    """Super-resolve ``recipe.input.image`` into ``out``; returns the
    metrics (those of ``metrics.json``). ``overwrite`` is the plan's
    business (an earlier run of another recipe)."""
    from tiledsm.cluster import compute_context
    from tiledsm.io import scene_rpc, write_geotiff_with_rpc, write_zarr
    from tiledsm.sr.recipe import product_name
    from tiledsm.workflows.common import write_json

    if plan is None or plan.product is None:  # called on its own, not by run_recipe
        from tiledsm.plan.core import new_plan
        from tiledsm.sr.plan import plan_sr

        plan = plan_sr(new_plan("run", out, cluster), recipe, cluster, overwrite=overwrite)
    hr = plan.product
    product = out / product_name(recipe)
    t0 = time.perf_counter()
    with compute_context(cluster or recipe.cluster.config()):
        if recipe.output.format == "zarr":
            write_zarr(hr, product)
        else:
            tags = {k: v for k, v in hr.attrs.items() if k.startswith("sr_")}
            write_geotiff_with_rpc(hr, product, scene_rpc(hr), nodata=float("nan"), dtype="float32", tags=tags)
    metrics = {
        "product": product.name,
        "shape": [hr.sizes["y"], hr.sizes["x"]],
        "sr": {k.removeprefix("sr_"): v for k, v in hr.attrs.items() if k.startswith("sr_")},
        "timings": {"sr_s": time.perf_counter() - t0},
        "warnings": list(plan.warnings),
    }
    write_json(metrics, out / "metrics.json")
    return metrics
