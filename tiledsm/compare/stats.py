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
  one bin width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "difference_statistics",
    "HistogramStats",
    "merge_partials",
    "SLOPE_CLASSES",
    "slope_class_labels",
]

#: default slope class lower bounds, in percent (demcompare's classes)
SLOPE_CLASSES = (0.0, 5.0, 10.0, 25.0, 45.0)

_NMAD_K = 1.4826


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
    def block(self, dh: np.ndarray, ref: np.ndarray, members: np.ndarray, evaluated: np.ndarray) -> dict:
        """Partial sums of one block.

        ``members``: bool ``(groups, rows, cols)``; ``evaluated``: bool
        ``(groups, rows, cols)`` cells that count in each group's
        completeness denominator.
        """
        G = len(self.groups)
        v = dh.astype(np.float64)
        finite = np.isfinite(v)
        idx = np.floor((v - self.lo) * (self.bins / (self.hi - self.lo)))
        idx = np.where(finite, np.clip(idx, -1, self.bins) + 1, 0).astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(v) / np.abs(ref.astype(np.float64))
        hist = np.zeros((G, self.bins + 2), dtype=np.int64)
        mom = np.zeros((G, 7))  # n, sum, sum2, sumabs, sumrel, nrel, evaluated
        ext = np.full((G, 2), [np.inf, -np.inf])
        for g in range(G):
            m = members[g] & finite
            vals = v[m]
            hist[g] = np.bincount(idx[m], minlength=self.bins + 2)
            r = rel[m]
            rf = np.isfinite(r)
            mom[g] = (vals.size, vals.sum(), (vals * vals).sum(), np.abs(vals).sum(), r[rf].sum(), rf.sum(), evaluated[g].sum())
            if vals.size:
                ext[g] = (vals.min(), vals.max())
        return {"hist": hist, "mom": mom, "ext": ext}

    @staticmethod
    def merge(a: dict, b: dict) -> dict:
        """Sum of two partial results."""
        return {
            "hist": a["hist"] + b["hist"],
            "mom": a["mom"] + b["mom"],
            "ext": np.column_stack([np.minimum(a["ext"][:, 0], b["ext"][:, 0]), np.maximum(a["ext"][:, 1], b["ext"][:, 1])]),
        }

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

    def finalize(self, part: dict, with_mre: bool = True) -> dict[str, dict]:
        """Statistics per group from the merged partial sums."""
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


def merge_partials(parts: list):
    """Pairwise (tree) reduction of delayed :class:`HistogramStats` partials
    into one delayed total (depth ``log2(len(parts))``, so no task receives
    every block at once)."""
    import dask

    while len(parts) > 1:
        parts = [
            dask.delayed(HistogramStats.merge, pure=True)(parts[i], parts[i + 1]) if i + 1 < len(parts) else parts[i]
            for i in range(0, len(parts), 2)
        ]
    return parts[0]
