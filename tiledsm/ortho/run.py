"""The runner of ``pipeline: ortho`` (``tiledsm ortho``, ``tiledsm run``)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from tiledsm.cluster import ClusterConfig
from tiledsm.ortho.recipe import OrthoRecipe

__all__ = ["run_ortho"]

log = logging.getLogger("tiledsm")


def run_ortho(recipe: OrthoRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False,
              plan=None) -> dict:
    """Run a ``pipeline: ortho`` recipe into ``out``; returns its metrics.

    The plan's lazy ortho (:func:`tiledsm.ortho.plan.plan_ortho`, made here
    when ``plan`` is not given) is computed into the resumable
    ``ortho.zarr`` (chunks an interrupted run of the same fingerprint
    finished are reused, ``overwrite`` discards them), then ``ortho.tif``,
    ``ortho.png`` and ``ortho.json`` (:func:`tiledsm.ortho.stage.write_ortho_products`);
    ``metrics.json`` (that report, ``pipeline``, the plan's warnings, the
    chunks reused) is written last, and withdrawn (with
    ``recipe.resolved.yaml``) before anything is written.
    :func:`tiledsm.pipelines.run_recipe` calls it inside the folder's lock.
    """
    from tiledsm.io import atomic_path, withdraw
    from tiledsm.ortho.stage import write_ortho_products

    out = Path(out)
    cluster = cluster or recipe.cluster.config()
    if plan is None or plan.product is None:
        from tiledsm.ortho.plan import plan_ortho
        from tiledsm.plan.core import new_plan

        plan = plan_ortho(new_plan("run", out, cluster), recipe, cluster, overwrite=overwrite)
    # the exports are rewritten, even from a finished store: nothing may describe them meanwhile
    withdraw(out, ["metrics.json", "recipe.resolved.yaml"])
    t0 = time.perf_counter()
    report = write_ortho_products(plan.product, out, cluster=cluster, warnings=plan.warnings, resume=True,
                                  overwrite=overwrite)
    chunks = report["timings"]["chunks"]
    if chunks["chunks_reused"]:
        print(f"{out / 'ortho.zarr'}: reused {chunks['chunks_reused']} of {chunks['chunks_total']} chunks "
              "from an earlier run")
    metrics = {"pipeline": "ortho", "out": str(out), **report}
    metrics["timings"]["total_s"] = time.perf_counter() - t0
    with atomic_path(out / "metrics.json") as tmp:
        Path(tmp).write_text(json.dumps(metrics, indent=2, default=str))
    log.info("metrics: %s", json.dumps(metrics, default=str))
    return metrics
