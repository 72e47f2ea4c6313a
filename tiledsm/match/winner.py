"""Winner-take-all over an aggregated cost volume (:mod:`tiledsm.match.sgm`):
each cell's best candidate with sub-step parabola refinement, its peak
ratio and its raw cost.

:func:`best_of_cell` is one cell's rule; :func:`winner_take_all` applies it
to a whole volume, and the fast aggregation
(:func:`tiledsm.match.sgm.aggregate_best`) to each cell as soon as its
last path is summed, so both give the same winners bit for bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["ABSENT", "best_of_cell", "winner_take_all"]

#: the aggregated cost of a candidate a cell does not have (a finite
#: stand-in for +inf, so that float32 sums of it stay ordered)
ABSENT = np.float32(3.0e38)
_INF = ABSENT


@nb.njit(nogil=True, cache=True, inline="always")
def best_of_cell(s, c, n, out, i, j):
    """The winner of cell ``(i, j)``: aggregated costs ``s`` (``(nd,)``),
    raw costs ``c``, ``n`` candidates (at most ``nd``); writes
    ``out = (index, smin, ratio, cbest)`` at ``[i, j]`` (see
    :func:`winner_take_all`)."""
    index, smin, ratio, cbest = out
    n = min(n, s.shape[0])
    kb = -1
    best = _INF
    for k in range(n):
        v = s[k]
        if v < best:
            best = v
            kb = k
    if kb < 0:
        index[i, j] = np.nan
        smin[i, j] = np.nan
        ratio[i, j] = np.nan
        cbest[i, j] = np.nan
        return
    # second best outside the winner's immediate neighbours
    second = _INF
    for k in range(n):
        if k < kb - 1 or k > kb + 1:
            v = s[k]
            if v < second:
                second = v
    off = 0.0
    if 0 < kb < n - 1:
        a = s[kb - 1]
        b = s[kb + 1]
        den = a - 2.0 * best + b
        if den > 0:
            off = 0.5 * (a - b) / den
    index[i, j] = kb + off
    smin[i, j] = best
    ratio[i, j] = best / second if second < _INF and second > 0 else 0.0
    cbest[i, j] = c[kb]


@nb.njit(nogil=True, cache=True)
def _wta(S, cost, nvalid, out):
    ny, nx, _ = S.shape
    for i in range(ny):
        for j in range(nx):
            best_of_cell(S[i, j], cost[i, j], nvalid[i, j], out, i, j)


def winner_take_all(
    S: np.ndarray, cost: np.ndarray | None = None, nvalid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Best candidate per cell with sub-step parabola refinement.

    Parameters
    ----------
    S : numpy.ndarray
        ``(ny, nx, nd)`` aggregated cost.
    cost : numpy.ndarray, optional
        The raw (unaggregated) cost volume, to report the raw cost of the
        winner; ``S`` itself when omitted.
    nvalid : numpy.ndarray, optional
        ``(ny, nx)`` number of candidates that exist in each cell
        (candidates ``k >= nvalid`` are ignored); ``nd`` when omitted.

    Returns
    -------
    index : numpy.ndarray
        ``(ny, nx)`` float32 sub-step index of the minimum, in
        ``[0, nd-1]`` (parabola through the minimum and its two neighbours;
        no refinement at the ends of the range).
    smin : numpy.ndarray
        Minimum aggregated cost.
    ratio : numpy.ndarray
        Peak ratio ``S_best / S_second`` (second best taken outside the
        winner's immediate neighbours) in ``[0, 1]``; close to 1 =
        ambiguous.
    cbest : numpy.ndarray
        Raw cost at the winning (integer) candidate; NaN if invalid.
    """
    S = np.ascontiguousarray(S, np.float32)
    ny, nx, nd = S.shape
    c = S if cost is None else np.ascontiguousarray(cost, np.float32)
    nv = np.full((ny, nx), nd, np.int64) if nvalid is None else np.ascontiguousarray(nvalid, np.int64)
    out = tuple(np.empty((ny, nx), np.float32) for _ in range(4))
    _wta(S, c, nv, out)
    return out
