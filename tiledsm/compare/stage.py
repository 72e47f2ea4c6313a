"""The DSM comparison stage: align, co-register, difference, measure, report.

``compare_dsms(ref, other, out_dir, spec, output)`` (the ``compare:`` and
``output:`` sections of the recipe, :mod:`tiledsm.compare.recipe`) writes
into ``out_dir``:

- ``dh.zarr``: Dataset on the common grid with ``dh`` (float32, metres,
  ``other_corrected - ref``, NaN = no difference), ``stable`` (uint8: 0 no
  difference, 1 stable terrain, 2 not stable) and ``slope_class`` (uint8
  index into ``spec.slope_classes`` from the reference slope in percent,
  255 = undefined);
- ``dh.tif``: the same ``dh`` as a Cloud-Optimised GeoTIFF (``output.cog``);
- ``dh.png`` (dh over the reference hillshade, with colour bar),
  ``dh_hist.png``, ``dh_slope_classes.png`` (``output.quicklook``);
- ``metrics.json``: ``coregistration: {dx, dy, dz, dx_px, dy_px, dx_m,
  dy_m, ...}`` and the statistics (all / stable / unstable / slope classes);
- ``report.html``: tables and the figures embedded (``output.report``).

Nothing is written before the inputs are validated and the co-registration
is fitted; products are written to a hidden staging folder inside
``out_dir`` and moved into place only when all of them succeeded.

Tiling: the common grid is chunked (``spec.chunk``); the shift is
applied with ``map_overlap`` (halo = ``ceil(|shift|)`` + kernel support),
slope with a halo of 1, polygon masks and the stable/slope-class layers with
``map_blocks`` (compiled kernels, same arithmetic as their numpy forms).
After the fit, **one pass** (one ``dask.compute``) writes ``dh.zarr`` and,
from the same ``dh`` blocks, reduces the statistics (per-block packed
histograms merged by ``da.reduction``) and gathers the strided arrays the
figures draw; ``dh.tif`` is then converted from the store one row of chunks
at a time, in a thread, while the figures are drawn. No process holds a
grid-sized array: memory per task is a few blocks and the client holds one
row of chunks, whatever the grid size.
Computation runs on the current dask scheduler (wrap the call in
:func:`tiledsm.cluster.compute_context`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
import uuid
from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path
from typing import Sequence

import dask
import dask.array as da
import numba
import numpy as np
import rioxarray  # noqa: F401  (registers .rio)
import xarray as xr
from affine import Affine

from tiledsm.allocator import heap_kept
from tiledsm.compare.align import AlignedPair, align_dsms, open_dsm
from tiledsm.compare.export import jsonable
from tiledsm.compare.coreg import (
    Coregistration,
    FitWindow,
    NoStableTerrainError,
    fit_deramp,
    get_coreg,
    shift_array,
    shift_halo,
)
from tiledsm.compare.recipe import CompareOutput, CompareSpec
from tiledsm.compare.stable import exclusion_mask, exclusion_mask_lazy, read_polygons
from tiledsm.compare.stats import HistogramStats, slope_class_labels
from tiledsm.compare.terrain import metric_steps, slope_percent
from tiledsm.errors import InputFileError, NoOverlapError
from tiledsm.io.export import exports_alongside

__all__ = ["CompareResult", "compare_dsms", "difference_lazy", "fit_coregistration"]

log = logging.getLogger("tiledsm.compare")

STABLE_NONE, STABLE_YES, STABLE_NO = 0, 1, 2
NO_CLASS = 255


@dataclass(frozen=True)
class CompareResult:
    """What :func:`compare_dsms` produced.

    Attributes
    ----------
    out_dir : Path
    coregistration : Coregistration
    metrics : dict
        The content of ``metrics.json``.
    products : dict
        Product name -> path.
    """

    out_dir: Path
    coregistration: Coregistration
    metrics: dict
    products: dict


# --------------------------------------------------------------------------- fit
def _fit_windows(pair: AlignedPair, geoms, spec: CompareSpec) -> list[FitWindow]:
    """Windows of the common grid loaded for the fit (all of it when small)."""
    H, W = pair.ref.shape
    if H * W <= spec.max_fit_pixels:
        boxes = [(0, H, 0, W)]
    else:
        ws = min(spec.fit_window, H, W)
        n = max(1, spec.max_fit_pixels // (ws * ws))
        ny = max(1, min(H // ws, round(math.sqrt(n * H / W))))
        nx = max(1, min(W // ws, n // ny))
        rs = np.linspace(0, H - ws, ny).astype(int)
        cs = np.linspace(0, W - ws, nx).astype(int)
        boxes = [(r, r + ws, c, c + ws) for r in rs for c in cs]
    slices = [(pair.ref.data[r0:r1, c0:c1], pair.other.data[r0:r1, c0:c1]) for r0, r1, c0, c1 in boxes]
    loaded = dask.compute(*slices)
    y = pair.ref.y.values
    windows = []
    for (r0, r1, c0, c1), (ref, oth) in zip(boxes, loaded):
        excluded = exclusion_mask(geoms, pair.transform @ Affine.translation(c0, r0), ref.shape)
        sx, sy = metric_steps(pair.crs, pair.transform, y[r0:r1])
        windows.append(FitWindow(ref, oth, ~excluded & np.isfinite(ref), sx, sy, r0, c0))
    _check_valid(pair, windows)
    return windows


def _check_valid(pair: AlignedPair, windows: list[FitWindow]) -> None:
    """All-NaN inputs and no common valid cell -> clear errors."""
    rname, oname = pair.ref.attrs["source"], pair.other.attrs["source"]
    if any(np.isfinite(w.ref).any() and np.isfinite(w.other).any() and (np.isfinite(w.ref) & np.isfinite(w.other)).any() for w in windows):
        return
    ref_ok, oth_ok, both = dask.compute(
        da.isfinite(pair.ref.data).any(),
        da.isfinite(pair.other.data).any(),
        (da.isfinite(pair.ref.data) & da.isfinite(pair.other.data)).any(),
    )
    if not ref_ok:
        raise InputFileError(f"{rname}: no valid height (all NaN/nodata) where it overlaps {oname}")
    if not oth_ok:
        raise InputFileError(f"{oname}: no valid height (all NaN/nodata) where it overlaps {rname}")
    if not both:
        raise NoOverlapError(f"{rname} and {oname}: their bounds overlap but no cell has a valid height in both")


def fit_coregistration(pair: AlignedPair, spec: CompareSpec = CompareSpec(), geoms=()) -> Coregistration:
    """Fit the co-registration of ``pair`` on its stable terrain (in memory).

    ``spec``: the method (``coreg``), its fit (``coreg_fit``, ``nmad_k``,
    ``deramp``) and the cells loaded for it (``max_fit_pixels``,
    ``fit_window``); ``geoms``: the exclusion polygons (of
    ``spec.stable_mask``) in the pair's CRS.
    """
    windows = _fit_windows(pair, list(geoms), spec)
    if not any(w.stable.any() for w in windows):
        raise NoStableTerrainError(
            f"no stable terrain left to co-register {pair.other.attrs['source']} on {pair.ref.attrs['source']}: "
            f"the exclusion polygons ({spec.stable_mask}) cover every valid cell"
        )
    coreg = get_coreg(spec.coreg)(windows, spec.coreg_fit, spec.nmad_k, spec.deramp)
    if spec.deramp:
        H, W = pair.ref.shape
        coreg = fit_deramp(windows, coreg, spec.coreg_fit, spec.nmad_k, ((H - 1) / 2, (W - 1) / 2))
    return coreg


# --------------------------------------------------------------------------- lazy difference
def _shift_block(block, dy, dx, kernel):
    return shift_array(block, dy, dx, kernel)


def _vertical_block(block, coreg: Coregistration, block_info=None):
    if not (coreg.ramp_col or coreg.ramp_row):  # the field is dz everywhere: no float64 block of it
        return (block + np.float64(coreg.dz)).astype(np.float32)
    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    rows = np.arange(r0, r1, dtype=np.float64)[:, None]
    cols = np.arange(c0, c1, dtype=np.float64)[None, :]
    return (block + coreg.vertical_field(rows, cols)).astype(np.float32)


def difference_lazy(pair: AlignedPair, coreg: Coregistration, kernel: str = "cubic") -> da.Array:
    """``dh = other_corrected - ref`` as a dask array (float32, metres)
    (see :func:`corrected_lazy`)."""
    return (corrected_lazy(pair, coreg, kernel) - pair.ref.data).astype(np.float32)


def corrected_lazy(pair: AlignedPair, coreg: Coregistration, kernel: str = "cubic") -> da.Array:
    """The other DSM corrected by ``coreg`` on the common grid, as a dask
    array (float32, metres).

    It is shifted by ``(coreg.dy_px, coreg.dx_px)`` with
    :func:`~tiledsm.compare.coreg.shift_array` in a ``map_overlap`` whose
    halo is :func:`~tiledsm.compare.coreg.shift_halo` (cells whose
    interpolation support leaves the common grid are NaN), then the
    vertical correction is added.
    """
    other = pair.other.data
    if coreg.dx_px or coreg.dy_px:
        halo = shift_halo(coreg.dy_px, coreg.dx_px, kernel)
        other = da.map_overlap(
            _shift_block, other, depth=halo, boundary=np.nan, dtype=np.float32,
            meta=np.empty((0, 0), np.float32), dy=coreg.dy_px, dx=coreg.dx_px, kernel=kernel,
        )
    if coreg.dz or coreg.ramp_col or coreg.ramp_row:
        other = da.map_blocks(_vertical_block, other, coreg, dtype=np.float32, meta=np.empty((0, 0), np.float32))
    return other.astype(np.float32)


def _slope_block(z, crs, transform, row0s, depth, block_info=None):
    """Slope (percent) of one block read with a halo of ``depth`` rows/columns.

    The rows' metric steps come from the grid (``row0s[i]``: first row of
    block ``i``), so no coordinate array travels with the blocks; the halo
    rows' own steps are never used (they are trimmed).
    """
    i = block_info[0]["chunk-location"][0]
    rows = row0s[i] - depth + np.arange(z.shape[0], dtype=np.float64)
    sx, sy = metric_steps(crs, transform, transform.f + transform.e * (rows + 0.5))
    return slope_percent(z, sx, sy).astype(np.float32)


def _slope_lazy(pair: AlignedPair) -> da.Array:
    """Reference slope (percent) by ``map_overlap`` (halo 1: Horn's 3 x 3 kernel)."""
    ref = pair.ref.data
    row0s = np.cumsum((0,) + ref.chunks[0][:-1])
    return da.map_overlap(
        partial(_slope_block, crs=pair.crs, transform=pair.transform, row0s=row0s, depth=1),
        ref, depth=1, boundary=np.nan, dtype=np.float32, meta=np.empty((0, 0), np.float32),
    )


def _class_block(slope_pct, excluded, dh, bounds, max_slope_deg, med, nmad_v, k):
    """``stack([stable, slope_class])`` (uint8) of one block, in one compiled pass.

    The rules of :func:`~tiledsm.compare.stable.stable_cells` with the
    arithmetic of its numpy form on float32 blocks: the slope limit as the
    float32 threshold :func:`max_slope_percent`, the outlier test
    ``|dh - med| <= k * nmad`` in float32 (Python scalars are weak in numpy).
    """
    out = np.empty((2,) + dh.shape, dtype=np.uint8)
    use_nmad = bool(nmad_v > 0)
    _classify(
        np.asarray(slope_pct, np.float32), np.asarray(excluded, bool), np.asarray(dh, np.float32),
        np.asarray(bounds, np.float64), max_slope_percent(max_slope_deg), np.float32(med),
        np.float32(k * nmad_v) if use_nmad else np.float32(0), use_nmad, out,
    )
    return out


@lru_cache(maxsize=16)
def max_slope_percent(max_slope_deg: float) -> np.float32:
    """The largest float32 slope (percent) ``p`` with ``degrees(arctan(p / 100)) <= max_slope_deg``
    evaluated by numpy in float32 (the test of the stable-terrain rule, as a threshold)."""

    def f(bits):
        p = bits.astype(np.int32).view(np.float32)
        return np.degrees(np.arctan(p / 100.0)) <= max_slope_deg

    lo, hi = 0, int(np.array(np.inf, np.float32).view(np.int32))  # bit patterns of 0 and +inf
    if not f(np.array([lo] * 16))[0]:
        return np.float32(-np.inf)
    if f(np.array([hi] * 16))[0]:
        return np.float32(np.inf)
    while hi - lo > 1:  # f(lo) true, f(hi) false; f is non-decreasing in p
        cand = np.unique(np.linspace(lo, hi, 4097).astype(np.int64))
        ok = f(cand)
        i = int(np.argmin(ok))  # first false
        lo, hi = int(cand[i - 1]), int(cand[i])
    return np.array([lo], np.int32).view(np.float32)[0]


@numba.njit(nogil=True, cache=True)
def _classify(slope_pct, excluded, dh, bounds, max_pct, med, tol, use_nmad, out):  # pragma: no cover - compiled
    H, W = dh.shape
    nb = bounds.size
    for i in range(H):
        for j in range(W):
            s = slope_pct[i, j]
            cls = NO_CLASS
            slope_ok = np.isfinite(s)
            if slope_ok:
                c = 0
                for b in range(nb):
                    if bounds[b] <= np.float64(s):
                        c = b + 1
                cls = c - 1
            v = dh[i, j]
            st = STABLE_NONE
            if np.isfinite(v):
                st = STABLE_NO
                if slope_ok and not excluded[i, j] and s <= max_pct:
                    if (abs(v - med) <= tol) if use_nmad else True:
                        st = STABLE_YES
            out[0, i, j] = st
            out[1, i, j] = cls


def _stats_groups(nclass: int) -> np.ndarray:
    """Groups (all, stable, unstable, stable by slope class) as unions of the cell
    classes of :func:`_stats_block`: stable in slope class ``c`` (``c``),
    stable without a class (``nclass``), not stable (``nclass + 1``)."""
    m = np.zeros((3 + nclass, nclass + 2), dtype=bool)
    m[0] = True
    m[1, : nclass + 1] = True
    m[2, nclass + 1] = True
    m[3:, :nclass] = np.eye(nclass, dtype=bool)
    return m


def _stats_block(dh, ref, st, cls, hs: HistogramStats, nclass: int) -> np.ndarray:
    """Packed statistics partial of one block: all, stable, unstable, stable by slope class."""
    codes = np.empty(st.shape, dtype=np.int64)
    _stats_codes(st, cls, nclass, codes)
    return hs.block_codes(dh, ref, codes, _stats_groups(nclass), np.isfinite(ref))


@numba.njit(nogil=True, cache=True)
def _stats_codes(st, cls, nclass, out):  # pragma: no cover - compiled
    H, W = st.shape
    for i in range(H):
        for j in range(W):
            if st[i, j] == STABLE_YES:
                out[i, j] = min(np.int64(cls[i, j]), nclass)
            elif st[i, j] == STABLE_NO:
                out[i, j] = nclass + 1
            else:
                out[i, j] = -1


# --------------------------------------------------------------------------- stage
def _as_input(x, chunks):
    if isinstance(x, (str, os.PathLike)):
        return open_dsm(x, chunks)
    if isinstance(x, xr.DataArray):
        if x.rio.crs is None:
            raise InputFileError(f"{x.attrs.get('source', x.name or '<in-memory DSM>')}: DSM has no CRS (write one with .rio.write_crs)")
        if "source" not in x.attrs:
            x = x.copy()
            x.attrs["source"] = x.name or "<in-memory DSM>"
        return x
    raise TypeError(f"expected a DSM path or an xarray.DataArray, got {type(x).__name__}")


def _move_into(staging: Path, out: Path) -> None:
    # metrics.json last: a kill between two moves never leaves it describing products not yet in place
    for item in sorted(staging.iterdir(), key=lambda p: p.name == "metrics.json"):
        final = out / item.name
        if final.exists():
            if final.is_dir():
                shutil.rmtree(final)
            else:
                final.unlink()
        os.rename(item, final)
    staging.rmdir()


def compare_dsms(ref, other, out_dir: str | Path, spec: CompareSpec = CompareSpec(),
                 output: CompareOutput = CompareOutput(), warnings: Sequence[str] = ()) -> CompareResult:
    """Compare two DSMs: co-register ``other`` on ``ref``, difference, measure, report.

    Parameters
    ----------
    ref, other : path or xr.DataArray
        Reference (e.g. pre-event) and other (post-event) DSMs: GeoTIFF /
        zarr paths, or georeferenced DataArrays (dask-backed for large
        grids; ``attrs['source']`` names them in messages). Heights in
        metres; any CRS and resolution (other is brought onto ref's grid).
    out_dir : path
        Output folder (created); products listed in the module notes.
    spec : CompareSpec
        The ``compare:`` section of the recipe: co-registration, stable
        terrain, statistics, chunking.
    output : CompareOutput
        The ``output:`` section: which of ``dh.tif``, the figures and
        ``report.html`` are written.
    warnings : sequence of str
        What the run's plan found worth saying, written into
        ``metrics.json`` (``warnings``).

    Returns
    -------
    CompareResult

    Raises
    ------
    InputFileError
        Unreadable DSM, no CRS, all-NaN DSM over the overlap, bad GeoJSON.
    NoOverlapError
        DSMs with no ground (or no valid cell) in common.
    NoStableTerrainError
        Masking left no stable terrain to fit the co-registration.
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    ref_da = _as_input(ref, spec.chunk)
    oth_da = _as_input(other, spec.chunk)
    pair = align_dsms(ref_da, oth_da, spec.chunk, spec.resampling)
    geoms = read_polygons(spec.stable_mask, pair.crs) if spec.stable_mask else []
    with heap_kept():  # the fit's window reads and iterations reuse their blocks (tiledsm.allocator)
        coreg = fit_coregistration(pair, spec, geoms)
    t_fit = time.perf_counter() - t0
    log.info("co-registration %s: dx=%.3f px dy=%.3f px dz=%.3f m", coreg.method, coreg.dx_px, coreg.dy_px, coreg.dz)

    # ---- lazy products
    dh = difference_lazy(pair, coreg, spec.coreg_fit.shift_kernel)
    slope = _slope_lazy(pair)
    excluded = exclusion_mask_lazy(geoms, pair.transform, pair.ref.data)
    layers = da.map_blocks(
        _class_block, slope, excluded, dh, np.asarray(spec.slope_classes, float), spec.max_slope_deg,
        coreg.median_after, coreg.nmad_after, spec.nmad_k,
        dtype=np.uint8, new_axis=0, chunks=((2,),) + dh.chunks, meta=np.empty((0, 0, 0), np.uint8),
    )
    coords = {"y": pair.ref.y, "x": pair.ref.x}
    ds = xr.Dataset(
        {
            "dh": (("y", "x"), dh, {"units": "m", "long_name": "other_corrected - ref"}),
            "stable": (("y", "x"), layers[0], {"flag_values": "0 1 2", "flag_meanings": "no_dh stable not_stable"}),
            "slope_class": (("y", "x"), layers[1], {"flag_values": "0..n-1 255", "lower_bounds_percent": json.dumps(list(spec.slope_classes))}),
        },
        coords=coords,
        attrs={"ref": pair.ref.attrs["source"], "other": pair.other.attrs["source"], "coregistration": json.dumps(jsonable(coreg.to_dict()))},
    )
    ds = ds.rio.write_crs(pair.crs).rio.write_transform(pair.transform)
    for var in ds.data_vars.values():  # no fill-value test of each chunk (a NaN-aware compare of the whole chunk)
        var.encoding["write_empty_chunks"] = True

    out.mkdir(parents=True, exist_ok=True)
    # a temporary's name (tiledsm.io.atomic.TEMPORARY): a killed run's staging is swept by the next run's lock
    staging = out / f".compare.tmp-{uuid.uuid4().hex[:10]}"
    staging.mkdir()
    try:
        products = _write_products(ds, pair, coreg, geoms, spec, output, staging, t0, t_fit, list(warnings))
        _move_into(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    metrics = json.loads((out / "metrics.json").read_text())
    return CompareResult(out, coreg, metrics, {k: out / Path(v).name for k, v in products.items()})


def _export_cog(staging: Path) -> None:
    """``dh.tif`` converted from the staged ``dh.zarr``."""
    from tiledsm.compare.export import cog_from_store
    from tiledsm.io import open_product

    cog_from_store(open_product(staging / "dh.zarr")["dh"], staging / "dh.tif")


def _write_products(ds, pair, coreg, geoms, spec: CompareSpec, output: CompareOutput, staging: Path, t0: float,
                    t_fit: float, warnings: list[str]) -> dict:
    """Write every product into ``staging``.

    One pass over the grid (one ``dask.compute``) writes ``dh.zarr`` and, from
    the same ``dh`` blocks, reduces the statistics (``da.reduction`` of
    per-block histograms) and gathers the strided (decimated) arrays the
    figures draw; the COG is then converted from the store in a thread while
    the figures are drawn (``timings_s``: ``cog`` and ``figures_report``
    overlap).
    """
    from tiledsm.io import write_zarr

    products = {}
    t1 = time.perf_counter()
    s = max(coreg.nmad_after, 0.01) if math.isfinite(coreg.nmad_after) else 1.0
    med = coreg.median_after if math.isfinite(coreg.median_after) else 0.0
    half = max(20.0 * s, 20.0)  # +-20 NMAD (>= 20 m): resolution NMAD/1600 with 65536 bins
    labels = slope_class_labels(spec.slope_classes)
    groups = ("all", "stable", "unstable") + tuple(f"slope {lab}" for lab in labels)
    hs = HistogramStats(groups, med - half, med + half, spec.hist_bins)
    dh_d = ds["dh"].data
    total = hs.lazy_total(
        partial(_stats_block, hs=hs, nclass=len(labels)),
        dh_d, pair.ref.data.rechunk(dh_d.chunks), ds["stable"].data, ds["slope_class"].data,
    )
    H, W = pair.ref.shape
    step = max(1, math.ceil(max(H, W) / output.quicklook_size))
    wanted = [total]
    if output.quicklook or output.report:
        wanted += [dh_d[::step, ::step], pair.ref.data[::step, ::step]]
    got: list = []

    def compute_all(store_delayed):
        got.extend(dask.compute(store_delayed, *wanted)[1:])

    with heap_kept():  # each block's reads, shifts and partials reuse the previous block's memory
        write_zarr(ds, staging / "dh.zarr", compute=compute_all)
    products["dh_zarr"] = staging / "dh.zarr"
    part = got[0]
    stats = hs.finalize(part)
    n_all = stats["all"]["count"]
    for name, st in stats.items():
        st["percent_of_valid"] = 100.0 * st["count"] / n_all if n_all else float("nan")
        if name != "all":
            st.pop("completeness", None)
            st.pop("cells", None)
    t_pass = time.perf_counter() - t1

    yc = float(pair.ref.y.values[H // 2])
    sx, sy = metric_steps(pair.crs, pair.transform, np.array([yc]))
    creg = coreg.ground(pair.crs, pair.transform, float(sx[0, 0]), float(sy[0, 0]))
    creg.update(
        method=coreg.method, iterations=coreg.iterations, converged=coreg.converged, n_samples=coreg.n_samples,
        ramp_col=coreg.ramp_col, ramp_row=coreg.ramp_row, ramp_origin=list(coreg.ramp_origin),
        fit_sample={"median_before": coreg.median_before, "nmad_before": coreg.nmad_before,
                    "median_after": coreg.median_after, "nmad_after": coreg.nmad_after},
        history_px=[list(h) for h in coreg.history],
    )
    metrics = {
        "ref": pair.ref.attrs["source"],
        "other": pair.other.attrs["source"],
        "dh_definition": "other_corrected - ref (m)",
        "grid": {
            "crs": pair.crs.to_string(), "transform": list(pair.transform)[:6], "width": W, "height": H,
            "ref_window": list(pair.ref_window), "other_resampled": pair.resampled,
            "metres_per_pixel": [abs(float(sx[0, 0])), abs(float(sy[0, 0]))],
        },
        "coregistration": creg,
        "statistics": {k: stats[k] for k in ("all", "stable", "unstable")},
        "slope_classes": {lab: stats[f"slope {lab}"] for lab in labels},
        "stable_terrain": {
            "exclusion_polygons": spec.stable_mask, "n_polygons": len(geoms), "max_slope_deg": spec.max_slope_deg,
            "outliers": f"|dh - {med:.4g}| > {spec.nmad_k} x {s:.4g}",
        },
        "params": {"compare": spec.model_dump(mode="json"), "output": output.model_dump(mode="json")},
        "histogram": {"lo": hs.lo, "hi": hs.hi, "bins": hs.bins, "median_nmad_resolution_m": (hs.hi - hs.lo) / hs.bins},
        "warnings": warnings,
    }

    # ---- exports: the COG (GDAL and compiled kernels, mostly without the GIL) in a thread while this
    # one draws the figures (matplotlib, mostly with it): the two overlap instead of adding up
    figures = {}
    with exports_alongside({"cog": lambda: _export_cog(staging)} if output.cog else {}) as seconds:
        t3 = time.perf_counter()
        if output.quicklook or output.report:
            from tiledsm.compare.report import make_figures

            figures = make_figures(got[1], got[2], step, pair, hs, hs.unpack(part), stats, labels, spec, geoms)
            if output.quicklook:
                for name, png in figures.items():
                    (staging / f"{name}.png").write_bytes(png)
                    products[name] = staging / f"{name}.png"
        t_fig = time.perf_counter() - t3
    t_cog = seconds.get("cog", 0.0)
    if output.cog:
        products["dh_tif"] = staging / "dh.tif"
    metrics["timings_s"] = {
        "fit": t_fit, "difference_statistics_zarr": t_pass, "cog": t_cog,
        "figures_report": t_fig, "total": time.perf_counter() - t0,
    }
    metrics = jsonable(metrics)
    (staging / "metrics.json").write_text(json.dumps(metrics, indent=2))
    products["metrics"] = staging / "metrics.json"
    if output.report:
        from tiledsm.compare.report import write_report

        write_report(staging / "report.html", metrics, figures)
        products["report"] = staging / "report.html"
    return products
