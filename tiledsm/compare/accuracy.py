"""Accuracy of a DSM against a reference DSM, computed chunk by chunk.

The reference is brought onto the DSM's grid (:func:`align_dsms`: sliced
when it shares the grid, else resampled bilinearly block by block) and the
statistics of ``d = dsm - reference`` are accumulated per chunk
(:class:`HistogramStats`): moments are exact, median and NMAD come from a
histogram spanning the measured range of ``d`` (bin width ``range / 2**18``).
So a DSM of any size is scored with the memory of a few chunks; on small
grids :func:`tiledsm.compare.stats.difference_statistics` gives the same
numbers exactly.

Conventions: heights and differences in metres; NaN = no height. A cell is
*evaluated* where the reference has a height (and the optional mask is
true); completeness is the fraction of evaluated cells where the DSM has a
height; MRE is the mean of ``|d| / |reference|``.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.compare.align import AlignedPair, align_dsms, open_dsm
from tiledsm.compare.stats import HistogramStats

__all__ = ["reference_accuracy", "grid_statistics"]

#: at most this many cells of the grid are loaded for the co-registration fit, in windows of this edge
FIT_CELLS = 1_000_000
FIT_CELLS_WINDOW = 256


def _partial(d: np.ndarray, ref: np.ndarray, mask: np.ndarray, hs: HistogramStats) -> np.ndarray:
    evaluated = np.isfinite(ref) & mask
    members = evaluated[None]
    return hs.block_packed(np.where(evaluated, d, np.nan), ref, members, members)


def reference_accuracy(
    dsm: xr.DataArray,
    reference: str | Path | xr.DataArray,
    mask: str | Path | xr.DataArray | None = None,
    *,
    chunks: int = 1024,
    bins: int = 2**18,
    coregister: bool = False,
) -> tuple[dict, xr.DataArray]:
    """Statistics of ``dsm - reference`` on the DSM's grid, lazily.

    Parameters
    ----------
    dsm : xarray.DataArray
        Heights ``(y, x)`` with CRS and transform (e.g. ``open_product(...)["height"]``),
        dask-backed or not; never resampled.
    reference : path or DataArray
        Reference heights (any CRS/resolution); resampled bilinearly onto
        the DSM's grid unless it shares it.
    mask : path or DataArray, optional
        Cells to evaluate (non-zero = evaluate), e.g. visible ground;
        resampled with nearest neighbour.
    chunks : int
        Chunk edge (cells) of the computation.
    bins : int
        Histogram bins for the median and NMAD.
    coregister : bool
        Also fit the horizontal offset between the two surfaces
        (Nuth & Kääb, :func:`tiledsm.compare.stage.fit_coregistration`)
        and score the DSM against the reference moved by it: two DSMs of
        the same scene made by different pipelines can sit a fraction of a
        cell apart (georeferencing conventions, orientation), which on
        slopes reads as height error. Reported under ``"coregistered"``
        next to the plain statistics, never instead of them.

    Returns
    -------
    stats : dict
        ``count, cells, completeness, mean, median, std, rmse, mae, nmad,
        min, max, mre`` (metres, MRE as a ratio); with ``coregister``
        also ``coregistered``: ``offset_east_m``, ``offset_north_m`` (where
        the DSM lies relative to the reference, metres), ``offset_px``
        (columns, rows), ``dz`` and the same statistics after the shift
        (but ``completeness``: the move's interpolation drops cells next
        to holes); only ``error`` (the reason) when no offset can be
        fitted (flat ground, too few common cells).
    difference : xarray.DataArray
        The lazy ``dsm - reference`` on the common grid (for a quick-look);
        ``attrs["window"]`` is ``(row0, row1, col0, col1)`` of that grid in
        the DSM.

    Raises
    ------
    NoOverlapError
        The reference covers no cell of the DSM.
    """
    ref = open_dsm(reference, chunks) if isinstance(reference, (str, Path)) else reference
    pair = align_dsms(dsm, ref, chunks=chunks)
    h, r = pair.ref.data, pair.other.data
    if mask is not None:
        m = open_dsm(mask, chunks) if isinstance(mask, (str, Path)) else mask
        keep = align_dsms(dsm, m, chunks=chunks, resampling="nearest").other.data
        keep = da.where(da.isnan(keep), False, keep > 0.5)
    else:
        keep = da.ones_like(h, dtype=bool)
    d = h - r
    diffs = [(d, r)]
    moved = error = None
    if coregister:
        from tiledsm.compare.coreg import CoregistrationError

        try:
            moved = _moved_back(pair, chunks)
            diffs.append(moved[1:])
        except CoregistrationError as exc:  # e.g. flat ground: no slope to fit an offset on; the plain stats stand
            error = str(exc)
    found = _statistics(diffs, keep, bins)
    stats = found[0]
    if moved is not None:
        stats["coregistered"] = _coregistered(pair, moved[0], found[1])
    elif error is not None:
        stats["coregistered"] = {"error": error}
    difference = pair.ref.copy(data=d)
    difference.attrs = {"long_name": "DSM - reference", "units": "m", "window": tuple(pair.ref_window)}
    return stats, difference


def grid_statistics(d: da.Array, reference: da.Array, keep: da.Array | None = None, bins: int = 2**18) -> dict:
    """Statistics of the differences ``d`` (metres, NaN = no height) where
    ``reference`` has a height and ``keep`` holds, chunk by chunk (``d``,
    ``reference`` and ``keep`` share their chunks): the keys of
    :func:`tiledsm.compare.stats.difference_statistics`; counts and
    moments exact, median and NMAD within two bins of ``range(d) / bins``.
    Two passes over the inputs (range, then histograms)."""
    keep = da.ones_like(reference, dtype=bool) if keep is None else keep
    return _statistics([(d, reference)], keep, bins)[0]


def _statistics(diffs: list[tuple[da.Array, da.Array]], keep: da.Array, bins: int) -> list[dict]:
    """Statistics of each difference ``d`` of ``diffs`` (with its
    reference ``r``) where ``r`` has a height and ``keep`` holds. Two
    passes over the inputs serve every difference: their ranges (the
    histograms' bins), then their histograms and moments."""
    ranges = dask.compute(*[x for d, _ in diffs for x in (da.nanmin(d), da.nanmax(d))])
    parts = []
    for (d, r), lo, hi in zip(diffs, ranges[0::2], ranges[1::2]):
        if not (np.isfinite(lo) and np.isfinite(hi)):
            lo, hi = -1.0, 1.0  # no finite difference: only counts matter
        pad = max(1e-3, 1e-6 * (hi - lo))
        hs = HistogramStats(("all",), float(lo) - pad, float(hi) + pad, bins)
        parts.append((hs, hs.lazy_total(partial(_partial, hs=hs), d, r, keep)))
    totals = dask.compute(*[total for _, total in parts])
    return [hs.finalize(total)["all"] for (hs, _), total in zip(parts, totals)]


def _moved_back(pair: AlignedPair, chunks: int):
    """``(coreg, moved - r, r)``: the horizontal offset of the DSM
    (``pair.ref``) relative to the reference (``pair.other``, on the DSM's
    grid), fitted on windows of the grid, and the lazy difference of the
    DSM moved back onto the reference by it. The DSM is moved, not the
    reference: a reference with many small holes (s2p's has 30 000) would
    lose most of its cells to the interpolation's support; bilinear, so a
    hole of the DSM grows by one cell at most."""
    from tiledsm.compare.coreg import CoregFitSpec
    from tiledsm.compare.recipe import CompareSpec
    from tiledsm.compare.stage import corrected_lazy, fit_coregistration

    onto_reference = align_dsms(pair.other, pair.ref, chunks=chunks)  # same grid: sliced, not resampled
    # the fit holds its windows in this process (a dozen float arrays per cell): 4 Mcells, compare's default,
    # made `tiledsm dsm --reference` 1.47x larger than without at 2048²; three parameters need far fewer cells
    spec = CompareSpec(coreg_fit=CoregFitSpec(shift_kernel="linear"), max_fit_pixels=FIT_CELLS,
                       fit_window=min(FIT_CELLS_WINDOW, chunks))
    coreg = fit_coregistration(onto_reference, spec)
    r = onto_reference.ref.data
    return coreg, corrected_lazy(onto_reference, coreg, kernel="linear") - r, r


def _coregistered(pair: AlignedPair, coreg, stats: dict) -> dict:
    """Where the DSM lies relative to the reference (``coreg``, the fit
    that moved it onto the reference) and ``stats`` of the moved DSM, on
    the cells the plain statistics evaluate."""
    from tiledsm.compare.terrain import metric_steps

    stats.pop("completeness")  # the move's interpolation drops cells next to holes: not the DSM's completeness
    # the fit moved the DSM onto the reference: the DSM lies the opposite way
    sx, sy = metric_steps(pair.crs, pair.transform, pair.ref.y.values[[len(pair.ref.y) // 2]])
    return {
        "method": coreg.method,
        "offset_east_m": -float(coreg.dx_px * float(np.mean(sx))),
        "offset_north_m": -float(coreg.dy_px * float(np.mean(sy))),
        "offset_px": [-float(coreg.dx_px), -float(coreg.dy_px)],
        "dz": -float(coreg.dz),
        "converged": bool(coreg.converged),
        **stats,
    }
