"""What the workflows share: the run log, withdrawing a run folder's
descriptions, writing the DSM products, a reference on a DSM's grid, DSM
metrics and JSON reports."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
import xarray as xr

from tiledsm.cluster import ClusterConfig, compute_context, compute_with_progress

log = logging.getLogger("tiledsm")

__all__ = [
    "DESCRIPTIONS", "DSM_EXPORTS", "DSM_DEFLATE_LEVEL", "setup_log", "withdraw_products", "dsm_metrics", "reference_on_grid",
    "write_dsm_products", "grid_chunk", "completeness", "write_json",
]


def setup_log(out: Path) -> logging.Handler:
    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "run.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger("tiledsm").addHandler(handler)
    logging.getLogger("tiledsm").setLevel(logging.INFO)
    return handler


#: files that describe a run folder's products; withdrawn while they change
DESCRIPTIONS = ("metrics.json", "recipe.resolved.yaml")
#: exports of the DSM store, rewritten from it at the end of a run
DSM_EXPORTS = ("dsm.tif", "dsm.png", "dsm_error.png")

#: DEFLATE level of ``dsm.tif`` (float heights, floating-point predictor).
#: Measured on the 4096² scene's DSM (``write_cog`` from its store, 2 cores,
#: three runs each): level 1 in 0.95-1.07 s into 42.8 MiB, GDAL's default (6)
#: in 1.61-1.63 s into 41.9 MiB. The export is on the command's critical
#: path; 2 % more bytes are not. ``dh.tif`` uses level 1 for the same reason.
DSM_DEFLATE_LEVEL = 1


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

    In memory (numpy-backed arrays), the statistics are exact
    (:func:`tiledsm.compare.stats.difference_statistics`). When any
    argument is dask-backed they stream chunk by chunk (the chunks of the
    first dask-backed one; :func:`tiledsm.compare.accuracy.grid_statistics`),
    so no process holds the grid: counts and moments are exact, median and
    NMAD within two histogram bins (bin = the differences' range / 2**18).
    """
    import dask.array as da

    lazy = [a for a in (height, reference, mask) if isinstance(getattr(a, "data", None), da.Array)]
    if lazy:
        from tiledsm.compare.accuracy import grid_statistics

        chunks = lazy[0].data.chunks
        h, ref = (da.asarray(getattr(a, "data", a)).rechunk(chunks) for a in (height, reference))
        keep = None if mask is None else da.asarray(getattr(mask, "data", mask)).astype(bool).rechunk(chunks)
        return grid_statistics(h.astype(np.float64) - ref.astype(np.float64), ref, keep)
    from tiledsm.compare.stats import difference_statistics

    ref = np.asarray(reference, dtype=np.float64)
    h = np.asarray(height, dtype=np.float64)
    sel = np.isfinite(ref)
    if mask is not None:
        sel &= np.asarray(mask, bool)
    return difference_statistics(h[sel] - ref[sel], reference=ref[sel])


def reference_on_grid(path: str | Path, like: xr.DataArray, resampling: str = "bilinear") -> xr.DataArray:
    """A reference raster on the grid of ``like``, lazily, with ``like``'s
    chunks (one block when ``like`` is in memory): sliced when it shares
    the grid, else resampled chunk by chunk, each task reading only the
    window of the file its chunk needs (``resampling``: a
    ``rasterio.enums.Resampling`` name; ``"nearest"`` for masks and
    labels). float32, NaN where the file has no value or does not reach.
    ``.values`` loads it; dask reductions stream it."""
    from tiledsm.compare.align import onto_grid, open_dsm

    chunk = max(like.data.chunks[0]) if like.chunks else 1024
    return onto_grid(open_dsm(path, chunk), like, resampling)


def write_dsm_products(
    ds: xr.Dataset,
    out: Path,
    *,
    cluster: ClusterConfig,
    cog: bool = True,
    quicklook: bool = True,
    overwrite: bool = False,
    alongside: Callable[[], None] | None = None,
) -> dict:
    """Compute the lazy DSM into ``out/dsm.zarr``, then COG and PNG.

    ``alongside``, if given, runs in this thread once the store is
    finished, while the COG and the PNG are written (e.g. the metrics
    against a reference, which read the store too).

    The store is resumable: chunks finished by an interrupted run are kept
    and only the others are computed (``overwrite`` discards them). So are
    the levels a staged graph matches into ``out/dsm.levels``
    (:mod:`tiledsm.dsm.stages`); that folder is removed once the DSM
    store is finished.

    Returns timings (with ``levels``: each staged level's chunks and how
    many were reused).
    """
    from tiledsm.allocator import heap_kept
    from tiledsm.dsm.stages import LEVELS_DIR, stage_reports
    from tiledsm.io import exports_alongside, write_cog, write_resumable
    from tiledsm.io.atomic import remove_path
    from tiledsm.quicklook import quicklook as make_quicklook

    timings: dict = {}
    t0 = time.perf_counter()
    chunks: dict = {}
    if overwrite:
        remove_path(out / LEVELS_DIR)
    # the matching tasks reuse their temporaries from the heaps; the exports after it start trimmed
    with compute_context(cluster) as client, heap_kept():
        write_resumable(
            ds,
            out / "dsm.zarr",
            compute=lambda delayed: compute_with_progress(delayed, config=cluster, client=client),
            overwrite=overwrite,
            report=chunks,
        )
    levels = stage_reports(out / LEVELS_DIR)
    # scratch: the finished store no longer needs its levels
    remove_path(out / LEVELS_DIR)
    timings["match_s"] = time.perf_counter() - t0
    timings["chunks"] = chunks
    if levels:
        timings["levels"] = levels
    if chunks.get("chunks_reused"):
        print(f"{out / 'dsm.zarr'}: reused {chunks['chunks_reused']} of {chunks['chunks_total']} chunks from an earlier run")
    for name, rep in levels.items():
        if rep["chunks_reused"]:
            print(f"{out / LEVELS_DIR / name}.zarr: reused {rep['chunks_reused']} of {rep['chunks_total']} matched "
                  "chunks from an earlier run")
    from tiledsm.io import open_product

    stored = open_product(out / "dsm.zarr")
    exports = {}
    if cog:
        exports["cog"] = lambda: write_cog(stored["height"], out / "dsm.tif", level=DSM_DEFLATE_LEVEL)
    if quicklook:
        exports["quicklook"] = lambda: make_quicklook(stored["height"], out / "dsm.png", kind="height",
                                                      title="DSM (m, ellipsoidal)")
    # the COG and the quick-look are written while the caller's work runs
    with exports_alongside(exports) as seconds:
        if alongside is not None:
            alongside()
    timings["export_s"] = max(seconds.values(), default=0.0)
    return timings


def grid_chunk(arr: xr.DataArray) -> int:
    """Chunk edge of a dask-backed ``(y, x)`` array (1024 when in memory)."""
    return int(arr.chunks[0][0]) if arr.chunks else 1024


def completeness(height: xr.DataArray, views, h_range) -> tuple[float, float]:
    """``(all, in_footprint)``: the fraction of the grid's cells that have
    a height, and of the cells seen by every view (cameras as used for
    matching; cells sampled every ``step`` rows/columns so at most ~1 M
    are projected). One pass over ``height`` gives both."""
    import dask

    from tiledsm.dsm import footprint_mask
    from tiledsm.io.grids import grid_like

    grid = grid_like(height)
    step = max(1, int(np.ceil(np.sqrt(height.size / 1e6))))
    inside = footprint_mask(grid, views, float(np.mean(h_range)), step)
    data = height.data
    whole, sample = dask.compute(np.isfinite(data).mean(), data[::step, ::step])
    sample = np.isfinite(np.asarray(sample))
    return float(whole), float(sample[inside].mean()) if inside.any() else 0.0


def write_json(obj: dict, path: Path) -> None:
    from tiledsm.io import atomic_path

    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=2, default=float))
