"""Recipe runners: one function per ``pipeline`` name, in a registry.

A runner takes a validated recipe and a run folder and leaves there the
stores, the products, ``recipe.resolved.yaml``, ``metrics.json`` and
``run.log``.
"""

from __future__ import annotations

import inspect
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
import xarray as xr

from tiledsm.cluster import ClusterConfig, compute_context, compute_with_progress
from tiledsm.recipes import DSMRecipe, dump_resolved

log = logging.getLogger("tiledsm")

__all__ = ["RUNNERS", "run_recipe", "withdraw_products", "write_dsm_products", "dsm_metrics", "grid_chunk"]

RUNNERS: dict[str, Callable] = {}


def _runner(name: str):
    def deco(fn):
        if name in RUNNERS:
            raise ValueError(f"pipeline {name!r} registered twice")
        RUNNERS[name] = fn
        return fn

    return deco


def _setup_log(out: Path) -> logging.Handler:
    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "run.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger("tiledsm").addHandler(handler)
    logging.getLogger("tiledsm").setLevel(logging.INFO)
    return handler


def run_recipe(
    recipe,
    out_dir: str | Path,
    cluster: ClusterConfig | None = None,
    overwrite: bool = False,
    *,
    plan=None,
    limits=None,
) -> dict:
    """Run a validated recipe into ``out_dir``; returns its metrics.

    The run is planned first (:func:`tiledsm.plan.plan_recipe`, unless
    ``plan`` is given): what cannot work is refused in seconds, before the
    folder is created, locked or any cluster started. The folder is then
    locked for the run (:class:`tiledsm.provenance.OutputLock`: a second
    run into it stops at once). Stores finished or left partial by an
    earlier run are resumed only when their fingerprint (inputs, RPCs,
    grid, parameters, code) equals this run's; otherwise the run stops
    naming what changed, unless ``overwrite``.

    ``metrics.json`` and ``recipe.resolved.yaml`` describe the products
    beside them: when the products are going to change (``overwrite``,
    another resolved recipe, a DSM store to compute or complete) both are
    withdrawn (with the DSM's exports) before anything is computed, and
    written again last, when the products are complete. So no
    interruption -- before the store exists, while it fills, after it is
    finished -- leaves them claiming products they do not describe.
    """
    from tiledsm.plan import Limits, plan_recipe
    from tiledsm.provenance import OutputLock

    out = Path(out_dir).expanduser().resolve()
    if plan is None:
        plan = plan_recipe(recipe, out, cluster, overwrite=overwrite, limits=limits or Limits())
    out.mkdir(parents=True, exist_ok=True)
    with OutputLock(out):
        handler = _setup_log(out)
        try:
            log.info("running pipeline %s into %s (overwrite: %s)", recipe.pipeline, out, overwrite)
            for message in plan.warnings:
                log.warning(message)
            withdraw_products(out, recipe, plan, overwrite)
            runner = RUNNERS[recipe.pipeline]
            extra = {"plan": plan} if "plan" in inspect.signature(runner).parameters else {}
            metrics = runner(recipe, out, cluster, overwrite=overwrite, **extra)
            dump_resolved(recipe, out / "recipe.resolved.yaml")
            return metrics
        finally:
            logging.getLogger("tiledsm").removeHandler(handler)
            handler.close()


#: files that describe a run folder's products; withdrawn while they change
DESCRIPTIONS = ("metrics.json", "recipe.resolved.yaml")
#: exports of the DSM store, rewritten from it at the end of a run
DSM_EXPORTS = ("dsm.tif", "dsm.png", "dsm_error.png")


def withdraw_products(out: Path, recipe, plan, overwrite: bool) -> list[str]:
    """Remove ``metrics.json`` and ``recipe.resolved.yaml`` (and, for a
    DSM, its exports) when this run is going to change the products: with
    ``overwrite``, when the resolved recipe differs from the one stored, or
    when the plan says the DSM store will be computed or completed
    (``plan.withdraw``). Returns the names removed."""
    import yaml

    stored = out / "recipe.resolved.yaml"
    try:
        same = yaml.safe_load(stored.read_text()) == recipe.model_dump(mode="json")
    except (OSError, yaml.YAMLError):
        same = False
    changes = overwrite or not same or (recipe.pipeline == "dsm" and plan.withdraw)
    if not changes:
        return []
    names = DESCRIPTIONS + (DSM_EXPORTS if recipe.pipeline == "dsm" else ())
    removed = [n for n in names if (out / n).is_file()]
    for n in removed:
        (out / n).unlink()
    if removed:
        log.info("withdrew %s: the products in %s are about to change", ", ".join(removed), out)
    return removed


def dsm_metrics(height: xr.DataArray, reference: xr.DataArray, mask: xr.DataArray | None = None) -> dict:
    """Error statistics of a DSM against a reference on the same grid.

    ``mask`` (True = evaluate) restricts the cells, e.g. to visible ground.
    Completeness is the fraction of evaluated cells that have a height.
    """
    from tiledsm.compare.stats import difference_statistics

    ref = reference.values.astype(np.float64)
    h = height.values.astype(np.float64)
    sel = np.isfinite(ref)
    if mask is not None:
        sel &= np.asarray(mask, bool)
    stats = difference_statistics(h[sel] - ref[sel], reference=ref[sel])
    return stats


def _reference_on_grid(path: str | Path, like: xr.DataArray, resampling: str = "bilinear") -> xr.DataArray:
    """A reference raster on the grid of ``like``: as is when it shares it,
    else resampled (``resampling``: a ``rasterio.enums.Resampling`` name;
    ``"nearest"`` for masks and labels)."""
    import rioxarray  # noqa: F401  (registers .rio)
    from rasterio.enums import Resampling

    ref = xr.open_dataarray(path, engine="rasterio", mask_and_scale=True).squeeze("band", drop=True)
    if ref.rio.crs == like.rio.crs and ref.shape == like.shape and np.allclose(ref.rio.transform(), like.rio.transform()):
        return ref.assign_coords(x=like.x, y=like.y)
    return ref.rio.reproject_match(like, resampling=Resampling[resampling])


def write_dsm_products(
    ds: xr.Dataset,
    out: Path,
    *,
    cluster: ClusterConfig,
    cog: bool = True,
    quicklook: bool = True,
    overwrite: bool = False,
) -> dict:
    """Compute the lazy DSM into ``out/dsm.zarr``, then COG and PNG.

    The store is resumable: chunks finished by an interrupted run are kept
    and only the others are computed (``overwrite`` discards them).

    Returns timings.
    """
    from tiledsm.io import write_cog, write_resumable
    from tiledsm.quicklook import quicklook as make_quicklook

    timings: dict = {}
    t0 = time.perf_counter()
    chunks: dict = {}
    with compute_context(cluster) as client:
        write_resumable(
            ds,
            out / "dsm.zarr",
            compute=lambda delayed: compute_with_progress(delayed, config=cluster, client=client),
            overwrite=overwrite,
            report=chunks,
        )
    timings["match_s"] = time.perf_counter() - t0
    timings["chunks"] = chunks
    if chunks.get("chunks_reused"):
        print(f"{out / 'dsm.zarr'}: reused {chunks['chunks_reused']} of {chunks['chunks_total']} chunks from an earlier run")
    from tiledsm.io import open_product

    stored = open_product(out / "dsm.zarr")
    t1 = time.perf_counter()
    if cog:
        write_cog(stored["height"], out / "dsm.tif")
    if quicklook:
        make_quicklook(stored["height"], out / "dsm.png", kind="height", title="DSM (m, ellipsoidal)")
    timings["export_s"] = time.perf_counter() - t1
    return timings


@_runner("dsm")
def run_dsm(
    recipe: DSMRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False, plan=None
) -> dict:
    """Views (or a synthetic scene) -> DSM products and metrics.

    ``plan`` (:func:`tiledsm.plan.plan_recipe`) carries the opened views, tie
    points and lazy DSM; without it (or for a synthetic scene, made here
    first) the run plans itself. Its warnings, and a low completeness, go
    to ``metrics.json`` (``warnings``).
    """
    from tiledsm.plan import LOW_COMPLETENESS, Limits, plan_recipe

    cluster = cluster or recipe.cluster.config()
    t_start = time.perf_counter()
    inp = recipe.input
    truth_mask = None
    orient_doc = None
    if recipe.orient is not None and inp.images is not None:
        # orient first; the DSM uses the corrected copies (a plan made on the original images is stale)
        from tiledsm.orient.spec import orient_for_recipe

        images, rpcs, orient_doc = orient_for_recipe(inp.images, inp.rpcs, recipe.orient, out / "orient", overwrite=overwrite)
        recipe = recipe.model_copy(update={"input": inp.model_copy(update={"images": images, "rpcs": rpcs})})
        inp, plan = recipe.input, None
    limits = plan.limits if plan is not None else Limits()
    if inp.synth is not None:
        from tiledsm.recipes import InputSpec
        from tiledsm.synth import make_scene

        sy = inp.synth
        log.info("making synthetic scene %s", sy.model_dump())
        scene = make_scene(out / "scene", size=sy.size, gsd=sy.gsd, bh=sy.bh, seed=sy.seed, views=sy.views, event=False)
        truth_mask = getattr(scene, "visible_mask", None)
        views_recipe = recipe.model_copy(update={"input": InputSpec(
            images=[str(p) for p in scene.views], reference=str(scene.truth_dsm))})
        plan = plan_recipe(views_recipe, out, cluster, overwrite=overwrite, limits=limits)
    elif plan is None or plan.prepared is None:
        plan = plan_recipe(recipe, out, cluster, overwrite=overwrite, limits=limits)
    prep = plan.prepared
    reference, report = prep.reference, prep.report
    timings = write_dsm_products(
        prep.ds, out, cluster=cluster, cog=recipe.output.cog, quicklook=recipe.output.quicklook, overwrite=overwrite
    )
    metrics: dict = {"pipeline": "dsm", "report": report, "timings": timings}
    if orient_doc is not None:
        metrics["orient"] = orient_doc
    from tiledsm.io import open_product

    height = open_product(out / "dsm.zarr")["height"]
    # lazy: the client never holds the whole DSM for this
    metrics["completeness"] = float(np.isfinite(height.data).mean().compute())
    metrics["completeness_in_footprint"] = _footprint_completeness(height, prep.views, prep.h_range)
    warnings = list(plan.warnings)
    if metrics["completeness_in_footprint"] < LOW_COMPLETENESS:
        warnings.append(
            f"low completeness: {metrics['completeness_in_footprint']:.0%} of the cells seen by every view have a "
            f"height (expected >= {LOW_COMPLETENESS:.0%}; check the height range and the images' overlap)"
        )
        log.warning(warnings[-1])
    if reference:
        # chunk by chunk: the client never holds the whole DSM or reference
        from tiledsm.compare.accuracy import reference_accuracy

        metrics["reference"] = str(reference)
        metrics["vs_reference"], error = reference_accuracy(height, reference, chunks=grid_chunk(height))
        if recipe.output.quicklook:
            from tiledsm.quicklook import quicklook

            r0, r1, c0, c1 = error.attrs["window"]
            quicklook(error, out / "dsm_error.png", kind="difference", title="DSM - reference (m)", dsm=height[r0:r1, c0:c1])
        if truth_mask is not None:
            metrics["vs_reference_visible"], _ = reference_accuracy(
                height, reference, truth_mask, chunks=grid_chunk(height)
            )
    metrics["warnings"] = warnings
    metrics["timings"]["total_s"] = time.perf_counter() - t_start
    metrics["output_mpx_per_s"] = height.size / 1e6 / max(timings["match_s"], 1e-9)
    _write_json(metrics, out / "metrics.json")
    log.info("metrics: %s", json.dumps(metrics))
    return metrics


def grid_chunk(arr: xr.DataArray) -> int:
    """Chunk edge of a dask-backed ``(y, x)`` array (1024 when in memory)."""
    return int(arr.chunks[0][0]) if arr.chunks else 1024


def _footprint_completeness(height: xr.DataArray, views, h_range) -> float:
    """Fraction of the cells seen by every view (cameras as used for
    matching) that have a height (cells sampled every ``step`` rows/columns
    so at most ~1 M are projected)."""
    from tiledsm.dsm import footprint_mask
    from tiledsm.geometry.grid import GroundGrid

    grid = GroundGrid.like(height)
    step = max(1, int(np.ceil(np.sqrt(height.size / 1e6))))
    inside = footprint_mask(grid, views, float(np.mean(h_range)), step)
    sample = np.isfinite(height[::step, ::step].values)
    return float(sample[inside].mean()) if inside.any() else 0.0


def _write_json(obj: dict, path: Path) -> None:
    from tiledsm.io import atomic_path

    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=2, default=float))


@_runner("train_sr")
def run_train_sr(recipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False) -> dict:
    """Train an SR network; the card (measured steps, time, PSNR) is the metrics."""
    from tiledsm.sr.train import TrainConfig, train

    values = dict(recipe.train)
    for key in ("cache_dirs", "blur_range", "noise_range"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    values.setdefault("out", str(out / f"{values.get('model', 'model')}.pt"))
    card = train(TrainConfig(**values))
    metrics = {"pipeline": "train_sr", "card": card}
    _write_json(metrics, out / "metrics.json")
    return metrics


# Workflows chaining several stages register their recipe schema and runner on
# import (explicit imports, no folder scanning).
from tiledsm.workflows import deformation as _deformation  # noqa: E402,F401
from tiledsm.workflows import sr_dsm as _sr_dsm  # noqa: E402,F401
from tiledsm.workflows import ortho_sr as _ortho_sr  # noqa: E402,F401
