"""Statistics of height differences ``dh = other - reference`` (metres).

Definitions (for the valid, i.e. finite, differences ``v``; ``r`` the
reference heights):

- mean, median, std (population, ``ddof=0``), min, max
- RMSE = ``sqrt(mean(v**2))``; MAE = ``mean(|v|)``
- MRE (mean relative error) = ``mean(|v| / |r|)`` — dimensionless, only
  when reference heights are given
- NMAD = ``1.4826 * median(|v - median(v)|)``
- count = number of valid differences; completeness = count / number of
  evaluated cells (NaN differences count as missing).

Two implementations share these definitions:

- :func:`difference_statistics`: exact, in memory (numpy).
- :class:`HistogramStats`: one lazy pass over a tiled grid (dask), several
  groups at once (all, stable, unstable, slope classes). Moments are exact
  (float64 sums); median and NMAD come from a fine histogram (bin width
  ``(hi - lo) / bins``, linearly interpolated), so they are exact to within
  one bin width. Per block, one compiled pass gives a packed partial (a
  float64 row per group: histogram, moments, extrema); the partials of all
  blocks are merged by ``da.reduction`` (:meth:`HistogramStats.lazy_total`),
  so the statistics are one more output of the pass that computes ``dh``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np

__all__ = [
    "difference_statistics",
    "HistogramStats",
    "SLOPE_CLASSES",
    "slope_class_labels",
]

#: default slope class lower bounds, in percent (demcompare's classes)
SLOPE_CLASSES = (0.0, 5.0, 10.0, 25.0, 45.0)

_NMAD_K = 1.4826
_NMOM = 7  # n, sum, sum2, sumabs, sumrel, nrel, evaluated


def slope_class_labels(bounds=SLOPE_CLASSES) -> list[str]:
    """Labels ``"[0%;5%["`` ... ``"[45%;inf["`` of the slope classes."""
    ups = list(bounds[1:]) + [np.inf]
    return [f"[{lo:g}%;{'inf' if np.isinf(hi) else f'{hi:g}%'}[" for lo, hi in zip(bounds, ups)]


def difference_statistics(dh, reference=None) -> dict:
    """Exact statistics of height differences (see the module notes).

    Parameters
    ----------
    dh : array_like
        Differences (metres); NaN = no value at an evaluated cell.
    reference : array_like, optional
        Reference heights at the same cells, for MRE.

    Returns
    -------
    dict
        mean, median, std, rmse, mae, nmad, min, max, count, cells,
        completeness (and mre with ``reference``); NaN values when no cell
        is valid.
    """
    v = np.asarray(dh, dtype=np.float64).ravel()
    cells = v.size
    ok = np.isfinite(v)
    r = None if reference is None else np.asarray(reference, dtype=np.float64).ravel()
    if r is not None:
        ok &= np.isfinite(r)
    v = v[ok]
    out = {"count": int(v.size), "cells": int(cells), "completeness": float(v.size / cells) if cells else float("nan")}
    if v.size == 0:
        out.update({k: float("nan") for k in ("mean", "median", "std", "rmse", "mae", "nmad", "min", "max")})
        if r is not None:
            out["mre"] = float("nan")
        return out
    med = float(np.median(v))
    out.update(
        mean=float(v.mean()),
        median=med,
        std=float(v.std()),
        rmse=float(np.sqrt(np.mean(v * v))),
        mae=float(np.mean(np.abs(v))),
        nmad=float(_NMAD_K * np.median(np.abs(v - med))),
        min=float(v.min()),
        max=float(v.max()),
    )
    if r is not None:
        with np.errstate(divide="ignore"):
            rel = np.abs(v) / np.abs(r[ok])
        out["mre"] = float(np.mean(rel[np.isfinite(rel)])) if np.isfinite(rel).any() else float("nan")
    return out


@dataclass(frozen=True)
class HistogramStats:
    """Lazy grouped statistics of ``dh`` over a tiled grid.

    Attributes
    ----------
    groups : tuple of str
        Group names; a block function gives, per cell, a boolean membership
        for each group (a cell may be in several).
    lo, hi : float
        Histogram range (metres); values outside fall in under/overflow bins
        (they still count for the median's rank).
    bins : int
        Histogram bins inside ``[lo, hi)``.
    """

    groups: tuple[str, ...]
    lo: float
    hi: float
    bins: int = 65536

    # ---- per block -------------------------------------------------------
    @property
    def width(self) -> int:
        """Columns of a packed partial: ``bins + 2`` histogram bins (under/overflow
        first/last), then n, sum, sum2, sumabs, sumrel, nrel, evaluated, min, max."""
        return self.bins + 2 + _NMOM + 2

    def block_packed(self, dh: np.ndarray, ref: np.ndarray, members: np.ndarray, evaluated: np.ndarray) -> np.ndarray:
        """Partial sums of one block, packed as a float64 ``(groups, width)`` array.

        ``members``: bool ``(groups, rows, cols)``; ``evaluated``: bool
        ``(groups, rows, cols)`` cells that count in each group's
        completeness denominator. Counts are exact in float64 (< 2**53).
        One compiled pass over the cells (:func:`_accumulate`).
        """
        out = np.zeros((len(self.groups), self.width))
        out[:, -2] = np.inf
        out[:, -1] = -np.inf
        _accumulate(
            np.ascontiguousarray(dh), np.ascontiguousarray(ref), np.ascontiguousarray(members, dtype=bool), np.ascontiguousarray(evaluated, dtype=bool),
            float(self.lo), float(self.bins / (self.hi - self.lo)), int(self.bins), out,
        )
        return out

    def block_codes(self, dh: np.ndarray, ref: np.ndarray, codes: np.ndarray, groups_of_code: np.ndarray,
                    evaluated: np.ndarray) -> np.ndarray:
        """:meth:`block_packed` for groups that are unions of disjoint cell classes.

        ``codes``: integer ``(rows, cols)``, each cell's class in
        ``[0, n_codes)`` (other values: in no group); ``groups_of_code``: bool
        ``(groups, n_codes)``, which classes make each group; ``evaluated``:
        bool ``(rows, cols)``, the completeness denominator shared by every
        group. One compiled pass fills one partial per class (a single
        histogram increment per cell); group partials are their sums (and
        min/max), so the cost does not grow with the number of groups.
        """
        M = np.asarray(groups_of_code, dtype=bool)
        per_code = np.zeros((M.shape[1], self.width))
        per_code[:, -2] = np.inf
        per_code[:, -1] = -np.inf
        _accumulate_codes(
            np.ascontiguousarray(dh), np.ascontiguousarray(ref), np.ascontiguousarray(codes, dtype=np.int64),
            float(self.lo), float(self.bins / (self.hi - self.lo)), int(self.bins), per_code,
        )
        out = np.stack([per_code[m, :-2].sum(axis=0) for m in M])
        out[:, self.bins + 2 + 6] = np.count_nonzero(evaluated)
        ext = np.where(M[:, :, None], per_code[None, :, -2:], np.array([np.inf, -np.inf]))
        return np.concatenate([out, ext[:, :, 0].min(axis=1)[:, None], ext[:, :, 1].max(axis=1)[:, None]], axis=1)

    def block(self, dh: np.ndarray, ref: np.ndarray, members: np.ndarray, evaluated: np.ndarray) -> dict:
        """:meth:`block_packed` as a dict ``{hist, mom, ext}`` (see :meth:`unpack`)."""
        return self.unpack(self.block_packed(dh, ref, members, evaluated))

    def unpack(self, packed: np.ndarray) -> dict:
        """``{"hist": int64 (groups, bins + 2), "mom": (groups, 7), "ext": (groups, 2)}`` of a packed partial."""
        b = self.bins + 2
        return {"hist": packed[:, :b].astype(np.int64), "mom": packed[:, b : b + _NMOM].copy(), "ext": packed[:, -2:].copy()}

    @staticmethod
    def merge(a: dict, b: dict) -> dict:
        """Sum of two partial results."""
        return {
            "hist": a["hist"] + b["hist"],
            "mom": a["mom"] + b["mom"],
            "ext": np.column_stack([np.minimum(a["ext"][:, 0], b["ext"][:, 0]), np.maximum(a["ext"][:, 1], b["ext"][:, 1])]),
        }

    # ---- over a tiled grid -----------------------------------------------
    def lazy_total(self, block_fn: Callable[..., np.ndarray], *arrays, split_every: int = 4):
        """Packed totals ``(groups, width)`` of ``block_fn`` over aligned dask arrays.

        ``block_fn(*blocks)`` gets the blocks of ``arrays`` (2-D, same
        chunks) and returns the block's packed partial (e.g. from
        :meth:`block_packed`). The partials form a ``(ny, nx, groups,
        width)`` array (``da.blockwise``) summed by ``da.reduction`` in a
        tree of ``split_every`` blocks per task (min/max for the extrema), so
        no task holds more than ``split_every`` partials.
        """
        import dask.array as da

        G, K = len(self.groups), self.width
        pairs = [x for a in arrays for x in (a, "ij")]
        parts = da.blockwise(
            _one_block, "ijgk", block_fn, None, *pairs, new_axes={"g": G, "k": K}, adjust_chunks={"i": 1, "j": 1},
            dtype=np.float64, meta=np.empty((0, 0, 0, 0), np.float64),
        )
        return da.reduction(
            parts, _keep, _merge_packed, axis=(0, 1), combine=_merge_packed, dtype=np.float64,
            split_every=split_every, concatenate=True,
            meta=np.empty((0, 0), np.float64),
        )

    # ---- final ------------------------------------------------------------
    def _quantile(self, hist: np.ndarray, q: float) -> float:
        """q-quantile from a histogram with under/overflow bins (linear in-bin)."""
        n = hist.sum()
        if n == 0:
            return float("nan")
        cum = np.cumsum(hist)
        target = q * n
        k = int(np.searchsorted(cum, target, side="left"))
        if k == 0 or k == self.bins + 1:
            return float("nan")  # falls in under/overflow
        w = (self.hi - self.lo) / self.bins
        before = cum[k - 1]
        frac = (target - before) / hist[k] if hist[k] else 0.5
        return float(self.lo + (k - 1 + frac) * w)

    def _nmad(self, hist: np.ndarray, med: float) -> float:
        if not np.isfinite(med):
            return float("nan")
        w = (self.hi - self.lo) / self.bins
        inner = hist[1:-1]
        centres = self.lo + (np.arange(self.bins) + 0.5) * w
        dev = np.abs(centres - med)
        order = np.argsort(dev, kind="stable")
        counts = inner[order]
        dev_s = dev[order]
        n = hist.sum()
        cum = np.cumsum(counts)
        target = 0.5 * n
        k = int(np.searchsorted(cum, target, side="left"))
        if k >= dev_s.size:
            return float("nan")  # more than half the values are out of range
        return float(_NMAD_K * dev_s[k])

    def finalize(self, part: dict | np.ndarray, with_mre: bool = True) -> dict[str, dict]:
        """Statistics per group from the merged partial sums (dict or packed array)."""
        if isinstance(part, np.ndarray):
            part = self.unpack(part)
        out = {}
        for g, name in enumerate(self.groups):
            n, s, s2, sa, sr, nr, ev = part["mom"][g]
            hist = part["hist"][g]
            stats = {"count": int(n), "cells": int(ev), "completeness": float(n / ev) if ev else float("nan")}
            if n == 0:
                stats.update({k: float("nan") for k in ("mean", "median", "std", "rmse", "mae", "nmad", "min", "max")})
            else:
                mean = s / n
                med = self._quantile(hist, 0.5)
                stats.update(
                    mean=float(mean),
                    median=med,
                    std=float(np.sqrt(max(s2 / n - mean * mean, 0.0))),
                    rmse=float(np.sqrt(s2 / n)),
                    mae=float(sa / n),
                    nmad=self._nmad(hist, med),
                    min=float(part["ext"][g, 0]),
                    max=float(part["ext"][g, 1]),
                )
            if with_mre:
                stats["mre"] = float(sr / nr) if nr else float("nan")
            out[name] = stats
        return out

    def histogram(self, part: dict, group: str, nbins: int = 200, lo: float | None = None, hi: float | None = None):
        """Coarser histogram ``(counts, edges)`` of one group for plotting."""
        g = self.groups.index(group)
        inner = part["hist"][g][1:-1]
        lo = self.lo if lo is None else lo
        hi = self.hi if hi is None else hi
        w = (self.hi - self.lo) / self.bins
        centres = self.lo + (np.arange(self.bins) + 0.5) * w
        return np.histogram(centres, bins=nbins, range=(lo, hi), weights=inner)


def _one_block(block_fn, *blocks) -> np.ndarray:
    return block_fn(*blocks)[None, None]


def _keep(x, axis=None, keepdims=True):
    return x


def _merge_packed(x: np.ndarray, axis=(0, 1), keepdims: bool = False) -> np.ndarray:
    """Merge packed partials along ``axis``: sums, then min and max of the extrema."""
    total = x[..., :-2].sum(axis=axis, keepdims=keepdims)
    lo = x[..., -2:-1].min(axis=axis, keepdims=keepdims)
    hi = x[..., -1:].max(axis=axis, keepdims=keepdims)
    return np.concatenate([total, lo, hi], axis=-1)


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _bin(v, lo, scale, bins):  # pragma: no cover - compiled
    """Histogram column of a finite ``v``: 0 underflow, ``bins + 1`` overflow."""
    t = np.floor((v - lo) * scale)
    return int(min(max(t, -1.0), np.float64(bins))) + 1


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _add(out, g, k, v, rel, m0):  # pragma: no cover - compiled
    """Add a finite value ``v`` (bin ``k``, relative error ``rel``) to row ``g`` of a packed partial."""
    out[g, k] += 1.0
    out[g, m0] += 1.0
    out[g, m0 + 1] += v
    out[g, m0 + 2] += v * v
    out[g, m0 + 3] += abs(v)
    if np.isfinite(rel):
        out[g, m0 + 4] += rel
        out[g, m0 + 5] += 1.0
    out[g, m0 + 7] = min(out[g, m0 + 7], v)
    out[g, m0 + 8] = max(out[g, m0 + 8], v)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _accumulate_codes(dh, ref, codes, lo, scale, bins, out):  # pragma: no cover - compiled
    """Add one block's cells to the packed partial of their class ``codes[i, j]`` (``out[code]``)."""
    H, W = dh.shape
    C = out.shape[0]
    for i in range(H):
        for j in range(W):
            g = codes[i, j]
            v = np.float64(dh[i, j])
            if 0 <= g < C and np.isfinite(v):
                _add(out, g, _bin(v, lo, scale, bins), v, abs(v) / abs(np.float64(ref[i, j])), bins + 2)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _accumulate(dh, ref, members, evaluated, lo, scale, bins, out):  # pragma: no cover - compiled
    """Add one block's cells to ``out`` (packed layout of :attr:`HistogramStats.width`)."""
    G, H, W = members.shape
    for i in range(H):
        for j in range(W):
            v = np.float64(dh[i, j])
            finite = np.isfinite(v)
            k = _bin(v, lo, scale, bins) if finite else 0
            rel = abs(v) / abs(np.float64(ref[i, j]))
            for g in range(G):
                if evaluated[g, i, j]:
                    out[g, bins + 2 + 6] += 1.0
                if finite and members[g, i, j]:
                    _add(out, g, k, v, rel, bins + 2)
