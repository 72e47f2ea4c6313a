"""Recipe runners: one function per ``pipeline`` name, in a registry.

A runner takes a validated recipe and a run folder and leaves there the
stores, the products, ``recipe.resolved.yaml``, ``metrics.json`` and
``run.log``.
"""

from __future__ import annotations

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

__all__ = ["RUNNERS", "run_recipe", "write_dsm_products", "dsm_metrics"]

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


def run_recipe(recipe, out_dir: str | Path, cluster: ClusterConfig | None = None, overwrite: bool = False) -> dict:
    """Run a validated recipe into ``out_dir``; returns its metrics.

    The folder is locked for the run (:class:`tiledsm.provenance.OutputLock`:
    a second run into it stops at once). Stores finished or left partial by
    an earlier run are resumed only when their fingerprint (inputs, RPCs,
    grid, parameters, code) equals this run's; otherwise the run stops
    naming what changed, unless ``overwrite``. ``recipe.resolved.yaml`` and
    ``metrics.json`` are written last, when the products are complete, so
    they never describe products of another run.
    """
    from tiledsm.provenance import OutputLock

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    with OutputLock(out):
        handler = _setup_log(out)
        try:
            log.info("running pipeline %s into %s (overwrite: %s)", recipe.pipeline, out, overwrite)
            metrics = RUNNERS[recipe.pipeline](recipe, out, cluster, overwrite=overwrite)
            dump_resolved(recipe, out / "recipe.resolved.yaml")
            return metrics
        finally:
            logging.getLogger("tiledsm").removeHandler(handler)
            handler.close()


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
def run_dsm(recipe: DSMRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False) -> dict:
    """Views (or a synthetic scene) -> DSM products and metrics."""
    from tiledsm.dsm import dsm_from_pair
    from tiledsm.recipes import dsm_params, grid_from_spec

    cluster = cluster or ClusterConfig(scheduler=recipe.cluster.scheduler, workers=recipe.cluster.workers)
    t_start = time.perf_counter()
    inp = recipe.input
    truth_mask = None
    if inp.synth is not None:
        from tiledsm.synth import make_scene

        sy = inp.synth
        log.info("making synthetic scene %s", sy.model_dump())
        scene = make_scene(out / "scene", size=sy.size, gsd=sy.gsd, bh=sy.bh, seed=sy.seed, views=sy.views, event=False)
        images = [str(p) for p in scene.views]
        rpcs = None
        reference = str(scene.truth_dsm)
        truth_mask = getattr(scene, "visible_mask", None)
    else:
        images, rpcs, reference = inp.images, inp.rpcs, inp.reference
    g = recipe.grid
    grid = grid_from_spec(g)
    params = dsm_params(g, recipe.match)
    ds, report = dsm_from_pair(*images, rpcs=rpcs, grid=grid, params=params)
    if recipe.output.geoid:
        from tiledsm.dsm import heights_above_geoid

        ds = heights_above_geoid(ds, recipe.output.geoid)
        report["vertical_datum"] = ds.attrs["vertical_datum"]
    timings = write_dsm_products(
        ds, out, cluster=cluster, cog=recipe.output.cog, quicklook=recipe.output.quicklook, overwrite=overwrite
    )
    metrics: dict = {"pipeline": "dsm", "report": report, "timings": timings}
    from tiledsm.io import open_product

    height = open_product(out / "dsm.zarr")["height"]
    # lazy: the client never holds the whole DSM for this
    metrics["completeness"] = float(np.isfinite(height.data).mean().compute())
    metrics["completeness_in_footprint"] = _footprint_completeness(height, images, rpcs, report["height_range_m"])
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
    metrics["timings"]["total_s"] = time.perf_counter() - t_start
    metrics["output_mpx_per_s"] = height.size / 1e6 / max(timings["match_s"], 1e-9)
    _write_json(metrics, out / "metrics.json")
    log.info("metrics: %s", json.dumps(metrics))
    return metrics


def grid_chunk(arr: xr.DataArray) -> int:
    """Chunk edge of a dask-backed ``(y, x)`` array (1024 when in memory)."""
    return int(arr.chunks[0][0]) if arr.chunks else 1024


def _footprint_completeness(height: xr.DataArray, images, rpcs, h_range) -> float:
    """Fraction of the cells seen by every view that have a height (cells
    sampled every ``step`` rows/columns so at most ~1 M are projected)."""
    from tiledsm.dsm import footprint_mask, open_views
    from tiledsm.geometry.grid import GroundGrid

    grid = GroundGrid.like(height)
    step = max(1, int(np.ceil(np.sqrt(height.size / 1e6))))
    views = open_views(images, rpcs)
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
