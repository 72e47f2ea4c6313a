"""Semi-global aggregation (8 paths) and winner-take-all over a cost volume.

Hirschmüller's semi-global matching, written for a cost volume whose
candidates may differ from cell to cell.

Candidate indexing (per-cell offsets)
-------------------------------------
The volume ``cost`` has shape ``(ny, nx, nd)``. Candidate ``k`` of cell
``(i, j)`` stands for the *absolute* label ``base[i, j] + k`` on one lattice
shared by all cells (in object space: the height ``(base + k) * step``; in
image space with ``base = 0``: the disparity ``d_min + k``). All cells have
the same number ``nd`` of candidates but their own ``base``; this is how a
coarse-to-fine search narrows the range around a coarser result cell by
cell.

Along a path, the transition from neighbour ``q`` (label ``l'``) to cell
``p`` (label ``l``) costs 0 if ``l == l'``, ``P1`` if ``|l - l'| == 1`` and
``P2`` otherwise, comparing absolute labels. So
``L_r(p, k) = C(p, k) + min(L_r(q, k+s), L_r(q, k+s±1) + P1,
min_k' L_r(q, k') + P2) - min_k' L_r(q, k')`` with ``s = base[p] - base[q]``;
entries of ``q`` outside ``0..nd-1`` are absent. With ``base = 0``
everywhere this is the textbook recursion.

A cell may have fewer candidates than the volume is deep: ``nvalid[i, j]``
says how many exist (``k < nvalid``); the others are absent from every
path (never a path's minimum, never a neighbour's predecessor), so a
cell's result does not depend on how deep a block pads its volume. A cell
with no candidates (``nvalid == 0``) is a gap: paths restart after it, as
at the volume's edge.

Costs that are NaN (invalid) are replaced by ``invalid_cost`` before
aggregation. Optional adaptive ``P2``: with a guide image ``g``,
``P2(p, q) = max(P1, P2 / (1 + |g(p) - g(q)| / p2_gamma))`` (smaller
penalty for jumps across intensity edges).

The aggregated cost ``S`` is the sum of the 8 path costs (directions
E, W, N, S and the four diagonals).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from tiledsm.match.paths import fast_passes, restarts
from tiledsm.match.winner import ABSENT as _INF
from tiledsm.match.winner import winner_take_all

__all__ = ["aggregate", "aggregate_best", "winner_take_all", "sgm", "remove_speckles"]



@nb.njit(nogil=True, cache=True, inline="always")
def _penalty2(P1, P2, guide, use_guide, gamma, i, j, pi, pj):
    if not use_guide:
        return P2
    d = abs(guide[i, j] - guide[pi, pj])
    if not np.isfinite(d):
        return P2
    p = P2 / (1.0 + d / gamma)
    return p if p > P1 else P1


@nb.njit(nogil=True, cache=True)
def _step(cost, i, j, prev, prev_min, shift, P1, P2, out, n):
    """One path update of the ``n`` candidates that exist; returns the
    minimum of ``out`` (+inf when ``n == 0``).

    ``prev`` and ``out`` are padded buffers: the ``nd`` path costs live at
    ``[pad : pad + nd]`` with ``pad = nd + 1`` and +inf around them, so that
    any ``|shift| <= nd`` reads inside the buffer without bounds checks;
    absent candidates (``k >= n``) are +inf too. The transition is the
    cheapest of staying, a one-label change (+``P1``) and any jump
    (+``P2``), taken relative to ``prev_min``: a jump beyond the
    neighbour's candidates then costs exactly ``P2`` however deep the
    buffer is. All in float32 (``P1`` and ``prev_min`` are float32, an
    adaptive ``P2`` is rounded to float32).
    """
    nd = cost.shape[2]
    pad = nd + 1
    best = _INF
    p2 = np.float32(P2)
    if shift > nd or shift < -nd:
        for k in range(n):
            o = cost[i, j, k] + p2
            out[pad + k] = o
            if o < best:
                best = o
    else:
        o0 = pad + shift
        for k in range(n):
            q = o0 + k
            m = min(prev[q], min(prev[q - 1], prev[q + 1]) + P1) - prev_min
            if p2 < m:
                m = p2
            o = cost[i, j, k] + m
            out[pad + k] = o
            if o < best:
                best = o
    for k in range(n, nd):
        out[pad + k] = _INF
    return best


@nb.njit(nogil=True, cache=True)
def _init(cost, i, j, out, n):
    nd = cost.shape[2]
    pad = nd + 1
    best = _INF
    for k in range(n):
        o = cost[i, j, k]
        out[pad + k] = o
        if o < best:
            best = o
    for k in range(n, nd):
        out[pad + k] = _INF
    return best


@nb.njit(nogil=True, cache=True, inline="always")
def _path_buffers(nx, nd):
    """Padding, padded width and the path buffers (costs, minima) of the
    previous and current row for the three row-crossing directions (dx =
    -1, 0, +1 relative to the sweep), +inf outside the candidates."""
    pad = nd + 1
    width = nd + 2 * pad
    prev = np.full((3, nx, width), _INF, np.float32)
    prev_min = np.empty((3, nx), np.float32)
    cur = np.full((3, nx, width), _INF, np.float32)
    cur_min = np.empty((3, nx), np.float32)
    return pad, width, prev, prev_min, cur, cur_min


@nb.njit(nogil=True, cache=True)
def _pass(cost, base, nvalid, P1, P2, guide, use_guide, gamma, S, forward, gi0, gj0, period):
    """Four paths in one sweep (rows top-down if ``forward`` else bottom-up).

    Cell ``[i, j]`` is cell ``[gi0 + i, gj0 + j]`` of the whole grid; with
    ``period > 0`` every path restarts on the grid's lines every
    ``period`` cells (see :func:`aggregate`), and after a cell without
    candidates."""
    ny, nx, nd = cost.shape
    sgn = 1 if forward else -1
    pad, width, prev, prev_min, cur, cur_min = _path_buffers(nx, nd)
    row = np.full(width, _INF, np.float32)
    row_new = np.full(width, _INF, np.float32)
    for t in range(ny):
        i = t if forward else ny - 1 - t
        pi = i - sgn
        # in-row path: left-to-right (forward) or right-to-left (backward)
        for u in range(nx):
            j = u if forward else nx - 1 - u
            n = nvalid[i, j]
            if u == 0 or restarts(gj0 + j, sgn, period) or nvalid[i, j - sgn] == 0:
                rmin = _init(cost, i, j, row, n)
            else:
                pj = j - sgn
                p2 = _penalty2(P1, P2, guide, use_guide, gamma, i, j, i, pj)
                rmin = _step(cost, i, j, row, rmin, base[i, j] - base[i, pj], P1, p2, row_new, n)
                row, row_new = row_new, row
            for k in range(nd):
                S[i, j, k] += row[pad + k]
        # row-crossing paths: from (pi, j - dx) for dx in (-1, 0, 1)
        for d in range(3):
            dx = d - 1
            for j in range(nx):
                pj = j - dx
                restart = restarts(gi0 + i, sgn, period) or (dx != 0 and restarts(gj0 + j, dx, period))
                n = nvalid[i, j]
                if t == 0 or pj < 0 or pj >= nx or restart or nvalid[pi, pj] == 0:
                    cur_min[d, j] = _init(cost, i, j, cur[d, j], n)
                else:
                    p2 = _penalty2(P1, P2, guide, use_guide, gamma, i, j, pi, pj)
                    cur_min[d, j] = _step(
                        cost, i, j, prev[d, pj], prev_min[d, pj], base[i, j] - base[pi, pj], P1, p2, cur[d, j], n
                    )
                for k in range(nd):
                    S[i, j, k] += cur[d, j, pad + k]
        prev, cur = cur, prev
        prev_min, cur_min = cur_min, prev_min


@nb.njit(nogil=True, cache=True)
def _fill_invalid(cost, value):
    ny, nx, nd = cost.shape
    out = np.empty((ny, nx, nd), np.float32)
    for i in range(ny):
        for j in range(nx):
            for k in range(nd):
                v = cost[i, j, k]
                out[i, j, k] = v if np.isfinite(v) else value
    return out


def check_penalties(P1: float, P2: float) -> None:
    """Raise ``ValueError`` unless ``0 <= P1 <= P2``."""
    if P2 < P1 or P1 < 0:
        raise ValueError(f"aggregate: need 0 <= P1 <= P2, got P1={P1}, P2={P2}")


def checked_layout(shape: tuple[int, int, int], P1: float, P2: float, base, nvalid) -> tuple[np.ndarray, np.ndarray]:
    """``base`` as int64 (zeros when ``None``) and ``nvalid`` as int64
    clipped to ``0..nd`` (``nd`` when ``None``) of a ``(ny, nx, nd)``
    volume, after checking their shapes and the penalties (a volume kept
    on a GPU is checked by its shape alone)."""
    check_penalties(P1, P2)
    ny, nx, nd = shape
    b = np.zeros((ny, nx), np.int64) if base is None else np.ascontiguousarray(base, np.int64)
    if b.shape != (ny, nx):
        raise ValueError(f"aggregate: base has shape {b.shape}, expected {(ny, nx)}")
    n = np.full((ny, nx), nd, np.int64) if nvalid is None else np.clip(np.asarray(nvalid, np.int64), 0, nd)
    if n.shape != (ny, nx):
        raise ValueError(f"aggregate: nvalid has shape {n.shape}, expected {(ny, nx)}")
    return b, np.ascontiguousarray(n)


def checked_volume(cost, P1: float, P2: float, base, nvalid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The volume as contiguous float32 and :func:`checked_layout`'s
    ``base`` and ``nvalid``, after checking the volume's shape."""
    cost = np.asarray(cost)
    if cost.ndim != 3 or min(cost.shape) < 1:
        raise ValueError(f"aggregate: cost volume must be (ny, nx, nd) and non-empty, got {cost.shape}")
    b, n = checked_layout(cost.shape, P1, P2, base, nvalid)
    return np.ascontiguousarray(cost, np.float32), b, n


def aggregate(
    cost: np.ndarray,
    P1: float,
    P2: float,
    base: np.ndarray | None = None,
    nvalid: np.ndarray | None = None,
    guide: np.ndarray | None = None,
    p2_gamma: float = 10.0,
    invalid_cost: float = 1.0,
    origin: tuple[int, int] = (0, 0),
    restart_period: int = 0,
    fast: bool = False,
) -> np.ndarray:
    """Semi-global aggregation of a cost volume over 8 paths.

    Parameters
    ----------
    cost : numpy.ndarray
        ``(ny, nx, nd)`` matching cost (float32; NaN = invalid).
    P1, P2 : float
        Penalties (cost units) for a one-label change and for a larger
        jump between path neighbours; ``P2 >= P1``.
    base : numpy.ndarray, optional
        ``(ny, nx)`` integer absolute label of candidate 0 of each cell (see
        the module docstring); zeros when omitted.
    nvalid : numpy.ndarray, optional
        ``(ny, nx)`` number of candidates each cell has (``k < nvalid``;
        the others are absent from the paths and their ``S`` is +inf; 0 =
        a gap the paths restart after); ``nd`` when omitted.
    guide : numpy.ndarray, optional
        ``(ny, nx)`` intensity image for the adaptive ``P2``.
    p2_gamma : float
        Intensity difference (guide units) that halves ``P2``.
    invalid_cost : float
        Cost given to NaN entries before aggregation.
    origin : (int, int)
        Index of cell ``[0, 0]`` in the whole grid (tiled runs).
    restart_period : int
        If > 0, every path restarts (from the cell's own cost, as at the
        volume's edge) when it enters a grid row or column whose global
        index is a multiple of ``restart_period`` (for paths running
        towards lower indices: the index + 1). A cell's aggregated cost
        then depends only on cells less than ``restart_period`` away along
        each path, so a tile computed with a halo of ``restart_period``
        cells gives exactly the whole-grid result on its core. (Plain
        semi-global matching lets a path carry information across the
        whole grid, most of all through textureless or invalid areas,
        where costs are flat: no finite halo makes tiles exact.)
    fast : bool
        Without a ``guide``: the compiled passes of the fast matching
        kernel (:func:`tiledsm.match.paths.fast_passes`), the same result
        bit for bit.

    Returns
    -------
    numpy.ndarray
        ``(ny, nx, nd)`` float32 aggregated cost ``S`` (sum of 8 paths);
        +inf for absent candidates.
    """
    cost, b, n = checked_volume(cost, P1, P2, base, nvalid)
    if fast and guide is None:
        return fast_passes(cost, b, n, P1, P2, invalid_cost, origin, restart_period)
    gi0, gj0, period = int(origin[0]), int(origin[1]), int(restart_period)
    ny, nx, _ = cost.shape
    c = _fill_invalid(cost, np.float32(invalid_cost))
    use_guide = guide is not None
    g = np.ascontiguousarray(guide, np.float32) if use_guide else np.zeros((1, 1), np.float32)
    if use_guide and g.shape != (ny, nx):
        raise ValueError(f"aggregate: guide has shape {g.shape}, expected {(ny, nx)}")
    S = np.zeros(c.shape, np.float32)
    p1, p2, gamma = np.float32(P1), np.float32(P2), np.float32(p2_gamma)
    _pass(c, b, n, p1, p2, g, use_guide, gamma, S, True, gi0, gj0, period)
    _pass(c, b, n, p1, p2, g, use_guide, gamma, S, False, gi0, gj0, period)
    return S


def aggregate_best(
    cost: np.ndarray,
    P1: float,
    P2: float,
    base: np.ndarray | None = None,
    nvalid: np.ndarray | None = None,
    invalid_cost: float = 1.0,
    origin: tuple[int, int] = (0, 0),
    restart_period: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`aggregate` (``fast``, no guide) then :func:`winner_take_all`
    against ``cost``, bit for bit, in one: the second pass takes each
    cell's winner as soon as its 8 path sums are complete, so ``S`` is
    never written back nor read again (on the 4096² scene's captured tasks,
    22 % less time for the coarsest task's aggregation and winners, 7 %
    for a level-0 task's).

    Returns
    -------
    index, smin, ratio, cbest : numpy.ndarray
        As :func:`winner_take_all`.
    """
    cost, b, n = checked_volume(cost, P1, P2, base, nvalid)
    out = tuple(np.empty(cost.shape[:2], np.float32) for _ in range(4))
    fast_passes(cost, b, n, P1, P2, invalid_cost, origin, restart_period, winners=out)
    return out


def sgm(cost: np.ndarray, P1: float, P2: float, base: np.ndarray | None = None, **kwargs):
    """:func:`aggregate` then :func:`winner_take_all` (same arguments; an
    ``nvalid`` goes to both); returns ``(index, smin, ratio, cbest)``."""
    S = aggregate(cost, P1, P2, base=base, **kwargs)
    return winner_take_all(S, cost, kwargs.get("nvalid"))


@nb.njit(nogil=True, cache=True)
def _speckles(values, max_diff, min_size, out):
    ny, nx = values.shape
    label = np.full((ny, nx), -1, np.int64)
    stack = np.empty(ny * nx, np.int64)
    members = np.empty(ny * nx, np.int64)
    di = np.array([-1, 1, 0, 0])
    dj = np.array([0, 0, -1, 1])
    cur = 0
    for i0 in range(ny):
        for j0 in range(nx):
            if label[i0, j0] >= 0 or not np.isfinite(values[i0, j0]):
                continue
            label[i0, j0] = cur
            top = 0
            stack[0] = i0 * nx + j0
            top = 1
            n = 0
            while top > 0:
                top -= 1
                p = stack[top]
                members[n] = p
                n += 1
                i = p // nx
                j = p - i * nx
                v = values[i, j]
                for t in range(4):
                    a = i + di[t]
                    b = j + dj[t]
                    if a < 0 or a >= ny or b < 0 or b >= nx or label[a, b] >= 0:
                        continue
                    w = values[a, b]
                    if np.isfinite(w) and abs(w - v) <= max_diff:
                        label[a, b] = cur
                        stack[top] = a * nx + b
                        top += 1
            if n < min_size:
                for m in range(n):
                    p = members[m]
                    out[p // nx, p - (p // nx) * nx] = np.nan
            cur += 1


def remove_speckles(values: np.ndarray, max_diff: float, min_size: int) -> np.ndarray:
    """Set small connected components of a height/disparity map to NaN.

    Two 4-neighbours belong to the same component when both are finite and
    differ by at most ``max_diff`` (same units as ``values``). Components
    with fewer than ``min_size`` cells are removed (as OpenCV's
    ``filterSpeckles``, but float and NaN-aware).

    Returns
    -------
    numpy.ndarray
        A float32 copy of ``values`` with the speckles set to NaN.
    """
    v = np.ascontiguousarray(values, np.float32)
    out = v.copy()
    if min_size > 1 and v.size:
        _speckles(v, np.float32(max_diff), int(min_size), out)
    return out
