"""The runner of ``pipeline: orient`` (``tiledsm orient``, ``tiledsm run``)."""

from __future__ import annotations

import json
import logging
import time
from contextlib import nullcontext
from pathlib import Path

from tiledsm.cluster import ClusterConfig
from tiledsm.orient.recipe import OrientRecipe

__all__ = ["run_orient"]

log = logging.getLogger("tiledsm")

#: what of ``orient.json`` ``metrics.json`` repeats (besides timings and warnings)
SUMMARY = ("images", "gcp_rms_px", "check_rms_px", "tie_relative_rms_px", "n_tracks", "n_rejected",
           "rejected_gcps", "datum")


def run_orient(recipe: OrientRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False,
               plan=None) -> dict:
    """Run a ``pipeline: orient`` recipe into ``out``; returns its metrics.

    The plan's opened images and DEM (:func:`tiledsm.orient.plan.plan_orient`,
    made here when ``plan`` is not given) are oriented
    (:func:`tiledsm.orient.stage.orient_images`: a cluster is started only
    for tie points) and the products written
    (:func:`tiledsm.orient.stage.write_orientation`: the earlier ones
    withdrawn first, ``orient.json`` last); ``metrics.json`` (the residuals
    of ``orient.json``, the datum, the warnings, timings) comes after, and
    is withdrawn (with ``recipe.resolved.yaml``) before anything is written. An
    orientation takes seconds: a rerun, after a kill too, computes it again
    (``overwrite`` changes nothing). :func:`tiledsm.pipelines.run_recipe`
    calls it inside the folder's lock.
    """
    from tiledsm.cluster import compute_context
    from tiledsm.io import atomic_path, withdraw
    from tiledsm.orient.stage import orient_images, write_orientation

    out = Path(out)
    cluster = cluster or recipe.cluster.config()
    if plan is None or plan.product is None:
        from tiledsm.orient.plan import plan_orient
        from tiledsm.plan.core import new_plan

        plan = plan_orient(new_plan("run", out, cluster), recipe, cluster, overwrite=overwrite)
    # the exports are rewritten, even from a finished store: nothing may describe them meanwhile
    withdraw(out, ["metrics.json", "recipe.resolved.yaml"])
    t0 = time.perf_counter()
    prepared, spec = plan.product, recipe.orient
    # the tie-point tiles are the only parallel part; GCP-only runs start no cluster
    with compute_context(cluster) if spec.tie_points and len(prepared.images) > 1 else nullcontext():
        o = orient_images(prepared.images, prepared.gcps, prepared.check_points, prepared.dem, spec,
                          rpcs=prepared.rpcs)
    datum_warning = [o.report["datum"]["warning"]] if "warning" in o.report["datum"] else []
    warnings = list(plan.warnings) + datum_warning
    for w in datum_warning:
        log.warning(w)
    doc = write_orientation(o, out, spec, extra={"command": "tiledsm orient", "warnings": warnings, "inputs": {
        "images": list(prepared.images), "gcps": prepared.gcps, "check_points": prepared.check_points,
        "dem": str(recipe.orient.dem) if recipe.orient.dem else None, "geoid": recipe.orient.geoid}})
    metrics = {"pipeline": "orient", **{k: doc[k] for k in SUMMARY if k in doc}, "warnings": warnings,
               "timings": {**o.report.get("timings_s", {}), "total_s": time.perf_counter() - t0}}
    with atomic_path(out / "metrics.json") as tmp:
        Path(tmp).write_text(json.dumps(metrics, indent=2, default=str))
    log.info("metrics: %s", json.dumps(metrics, default=str))
    return metrics
