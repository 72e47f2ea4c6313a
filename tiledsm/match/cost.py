"""Matching costs between images sampled on a common grid.

The object-space matcher (:mod:`tiledsm.match.sgvll`) samples every view at
the projections of the same ground cells for one candidate height, which
gives co-registered 2-D arrays; the image-space matcher the tests validate
these kernels with (``tests/match/stereo.py``) shifts the right image by a
candidate disparity. In both cases the cost of a candidate is computed here from two
such arrays, cell by cell, over a square window.

Conventions
-----------
- Inputs are ``float32`` arrays of identical shape ``(ny, nx)``; NaN marks
  nodata (outside the image, masked pixels).
- ``cost = 1 - ZNCC``, in ``[0, 2]`` (0 = perfect correlation). A cell whose
  window holds any NaN, or whose window is flat in either image (variance
  below ``eps`` times the squared mean intensity scale), gets NaN: an
  *invalid* cost, which the aggregation replaces by a neutral value.
- The window is ``(2 * half + 1)`` cells square, centred on the cell; cells
  closer than ``half`` to the array border are invalid (NaN).

All kernels are numba ``nogil`` functions, safe to run in threads.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["zncc_cost", "mean_zncc_cost", "COSTS"]


@nb.njit(nogil=True, cache=True)
def _zncc_kernel(a, b, half, eps, out):
    """Write 1 - ZNCC of windows of a and b into ``out`` (NaN where invalid).

    Window sums are computed afresh for every cell (column sums of the
    window's rows, then their sum), never as running or summed-area totals:
    a cell's cost then depends only on the values inside its window, in a
    fixed order, so overlapping blocks of a tiled computation give
    bit-identical costs wherever their windows coincide. (Summed-area
    tables depend on the block origin through rounding, and lose precision
    by cancellation on large blocks.)
    """
    ny, nx = a.shape
    w = 2 * half + 1
    n = w * w
    inv_n = 1.0 / n
    for i in range(ny):
        for j in range(nx):
            out[i, j] = np.nan
    if ny < w or nx < w:
        return
    # per column: sums over the w rows of the current window position
    ca = np.empty(nx)
    cb = np.empty(nx)
    caa = np.empty(nx)
    cbb = np.empty(nx)
    cab = np.empty(nx)
    cbad = np.empty(nx, np.int64)
    for i in range(half, ny - half):
        for j in range(nx):
            sa = 0.0
            sb = 0.0
            saa = 0.0
            sbb = 0.0
            sab = 0.0
            bad = 0
            for r in range(i - half, i + half + 1):
                x = np.float64(a[r, j])
                y = np.float64(b[r, j])
                if np.isfinite(x) and np.isfinite(y):
                    sa += x
                    sb += y
                    saa += x * x
                    sbb += y * y
                    sab += x * y
                else:
                    bad += 1
            ca[j] = sa
            cb[j] = sb
            caa[j] = saa
            cbb[j] = sbb
            cab[j] = sab
            cbad[j] = bad
        for j in range(half, nx - half):
            bad = 0
            for c in range(j - half, j + half + 1):
                bad += cbad[c]
            if bad != 0:
                continue
            s_a = 0.0
            s_b = 0.0
            s_aa = 0.0
            s_bb = 0.0
            s_ab = 0.0
            for c in range(j - half, j + half + 1):
                s_a += ca[c]
                s_b += cb[c]
                s_aa += caa[c]
                s_bb += cbb[c]
                s_ab += cab[c]
            va = s_aa - s_a * s_a * inv_n
            vb = s_bb - s_b * s_b * inv_n
            # flat windows carry no information
            if va <= eps * (1.0 + s_aa) or vb <= eps * (1.0 + s_bb):
                continue
            c = (s_ab - s_a * s_b * inv_n) / np.sqrt(va * vb)
            if c > 1.0:
                c = 1.0
            elif c < -1.0:
                c = -1.0
            out[i, j] = 1.0 - c


def zncc_cost(a: np.ndarray, b: np.ndarray, half: int, eps: float = 1e-6, out: np.ndarray | None = None) -> np.ndarray:
    """Windowed ``1 - ZNCC`` between two co-registered images.

    Parameters
    ----------
    a, b : numpy.ndarray
        ``(ny, nx)`` arrays (converted to float32), NaN = nodata.
    half : int
        Half window size: the window is ``2*half+1`` cells square.
    eps : float
        Relative variance floor: a window whose variance is below
        ``eps * (1 + sum of squares)`` is flat and gives NaN.
    out : numpy.ndarray, optional
        ``(ny, nx)`` float32 array to write into (may be a strided view, for
        instance ``volume[:, :, k]``).

    Returns
    -------
    numpy.ndarray
        ``(ny, nx)`` float32 cost in ``[0, 2]``; NaN where invalid (window
        touching nodata or the border, or flat).
    """
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"zncc_cost: images must be 2-D and of equal shape, got {a.shape} and {b.shape}")
    if half < 0:
        raise ValueError(f"zncc_cost: half window must be >= 0, got {half}")
    if out is None:
        out = np.empty(a.shape, np.float32)
    _zncc_kernel(a, b, int(half), float(eps), out)
    return out


def mean_zncc_cost(
    samples: list[np.ndarray], half: int, out: np.ndarray | None = None, weights: np.ndarray | None = None
) -> np.ndarray:
    """Multi-view cost: ``1 - weighted mean ZNCC`` over all view pairs,
    ignoring invalid pairs (occluded or outside one view).

    Parameters
    ----------
    samples : list of numpy.ndarray
        Two or more co-registered ``(ny, nx)`` float32 arrays (one per view,
        sampled at the projections of the same ground cells).
    half : int
        Half window size, cells.
    out : numpy.ndarray, optional
        Destination ``(ny, nx)`` float32 array (may be strided).
    weights : numpy.ndarray, optional
        ``(n, n)`` weight of pair ``(i, j)`` (upper triangle read), e.g. the
        pair's parallax per metre of height, so that a narrow-baseline pair,
        whose correlation peak is wide in height, does not flatten the
        minimum of a wide one. Default: equal weights.

    Returns
    -------
    numpy.ndarray
        ``(ny, nx)`` float32 in ``[0, 2]``, NaN where no pair is valid.
    """
    n = len(samples)
    if n < 2:
        raise ValueError(f"mean_zncc_cost: need at least two views, got {n}")
    if n == 2:
        return zncc_cost(samples[0], samples[1], half, out=out)
    w = np.ones((n, n), np.float32) if weights is None else np.asarray(weights, np.float32)
    if w.shape != (n, n):
        raise ValueError(f"mean_zncc_cost: weights must be ({n}, {n}), got {w.shape}")
    total = np.zeros(samples[0].shape, np.float32)
    count = np.zeros(samples[0].shape, np.float32)
    tmp = np.empty(samples[0].shape, np.float32)
    for i in range(n):
        for j in range(i + 1, n):
            zncc_cost(samples[i], samples[j], half, out=tmp)
            ok = np.isfinite(tmp)
            total[ok] += w[i, j] * tmp[ok]
            count[ok] += w[i, j]
    with np.errstate(invalid="ignore", divide="ignore"):
        res = (total / count).astype(np.float32)
    if out is None:
        return res
    out[...] = res
    return out


#: Registry of two-image costs (name -> callable(a, b, half, out=None)).
COSTS: dict[str, object] = {"zncc": zncc_cost}
