"""Resolving power on a stripe chart.

A stripe group of bar width ``k`` cells (bars varying along x) is
*resolved* when the Michelson contrast of its stripes,
``(Imax - Imin) / (Imax + Imin)``, is at least ``threshold`` (0.1). The
contrast is measured at the stripes' own frequency: the column profile
(mean over the group's rows, 2 cells trimmed at each end) is fitted by
least squares with ``m + a cos(pi x / k) + b sin(pi x / k)`` and the
contrast is ``sqrt(a^2 + b^2) / m`` (spurious detail at other
frequencies, e.g. aliasing, does not count as resolution).
"""

from __future__ import annotations

import numpy as np

__all__ = ["stripe_contrast", "resolved_px"]


def stripe_contrast(image: np.ndarray, group: tuple[int, int, int, int, int]) -> float:
    """Michelson contrast of one stripe group ``(k, row0, row1, col0, col1)``
    (module docstring); NaN when the group has no value."""
    k, r0, r1, c0, c1 = group
    patch = np.asarray(image, float)[r0 + 2:r1 - 2, c0:c1]
    prof = np.nanmean(patch, axis=0) if np.isfinite(patch).any() else np.full(c1 - c0, np.nan)
    x = np.arange(c1 - c0) + 0.5
    ok = np.isfinite(prof)
    if ok.sum() < 4:
        return float("nan")
    w = np.pi / k
    A = np.stack([np.ones(ok.sum()), np.cos(w * x[ok]), np.sin(w * x[ok])], 1)
    (m, a, b), *_ = np.linalg.lstsq(A, prof[ok], rcond=None)
    return float(np.hypot(a, b) / m) if m > 0 else float("nan")


def resolved_px(image: np.ndarray, chart, threshold: float = 0.1) -> int | None:
    """Narrowest bar width ``k`` (HR cells) such that every group at least
    as wide has contrast >= ``threshold``; None when even the widest fails."""
    groups = sorted(chart, key=lambda g: g[0])
    best = None
    for g in reversed(groups):
        c = stripe_contrast(image, g)
        if not (c >= threshold):
            break
        best = g[0]
    return best
