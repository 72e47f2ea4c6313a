"""The semi-global paths of the fast matching kernel: the two passes of
:func:`tiledsm.match.sgm.aggregate` (``fast=True``) and
:func:`tiledsm.match.sgm.aggregate_best`, bit for bit those of the
reference passes there (``_pass``), compiled for speed.

Conventions (absolute labels ``base + k``, ``nvalid`` candidates per cell,
+inf for absent ones, path restarts every ``period`` grid lines) are those
of :mod:`tiledsm.match.sgm`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from tiledsm.match.winner import ABSENT as _INF
from tiledsm.match.winner import best_of_cell

__all__ = ["fast_passes", "restarts"]

#: the winners' outputs of a pass that takes none (:func:`_pass_fast`)
_NO_WINNERS = tuple(np.empty((0, 0), np.float32) for _ in range(4))


@nb.njit(nogil=True, cache=True, inline="always")
def restarts(g, sgn, period):
    """Whether a path moving by ``sgn`` along an axis restarts at global
    index ``g``: it does on entering every ``period``-th line (from either
    side), so its memory never spans more than ``period`` cells."""
    if period <= 0:
        return False
    if sgn > 0:
        return g % period == 0
    return (g + 1) % period == 0


def fast_passes(cost, b, n, P1, P2, invalid_cost, origin, restart_period, winners=None) -> np.ndarray:
    """The two passes of the fast aggregation on a checked volume
    (:func:`tiledsm.match.sgm.checked_volume`); returns ``S`` (complete
    unless ``winners``, the four arrays the second pass then fills
    instead)."""
    gi0, gj0, period = int(origin[0]), int(origin[1]), int(restart_period)
    S = np.zeros(cost.shape, np.float32)
    p1, p2, inv = np.float32(P1), np.float32(P2), np.float32(invalid_cost)
    ny, nx, nd = cost.shape
    _pass_fast(cost, b, n, p1, p2, S, True, gi0, gj0, period, inv, False, _NO_WINNERS, _fast_scratch(nx, nd))
    last = _NO_WINNERS if winners is None else winners
    _pass_fast(cost, b, n, p1, p2, S, False, gi0, gj0, period, inv, winners is not None, last, _fast_scratch(nx, nd))
    return S


# ------------------------------------------------------------ compiled fast path
# The helpers are inlined into _pass_fast (numba IR). _pass_fast is compiled
# without the runtime's reference counting (_nrt=False; it allocates
# nothing, _fast_scratch does): numba could not prune the counts of its
# per-cell array views, an atomic increment and decrement each
# (NRT_incref/NRT_decref held 7 % of the perf samples of a task's kernels).
#
# A path's costs of one cell live in a slot of a row buffer: candidate k at
# [pad + k], +inf around (see _fast_buffers). The slots are short (a few
# guard entries on each side, not a whole volume's depth as in _pass): the
# buffers of a row stay in the core's cache. A neighbour whose labels are
# shifted by more than the guard is read with explicit bounds instead.

#: label shifts between path neighbours read through a slot's +inf guard
#: entries; larger ones (rare: steep jumps of the search band) read with
#: bounds (:func:`_step_bounded`)
_GUARD = 4

#: candidates a fixed-lane update computes at once (a constant trip count
#: vectorises whole): cells with at most this many take it
_LANES = 16


def _fast_buffers(nx, nd):
    """Padding, slot width and the path buffers (costs, minima) of the
    previous and current row for the three row-crossing directions: slots
    of ``pad + max(nd, _LANES) + _GUARD + 2`` entries, +inf outside a
    cell's candidates."""
    pad = _GUARD + 1
    width = pad + max(nd, _LANES) + _GUARD + 2
    prev = np.full((3, nx, width), _INF, np.float32)
    prev_min = np.empty((3, nx), np.float32)
    cur = np.full((3, nx, width), _INF, np.float32)
    cur_min = np.empty((3, nx), np.float32)
    return pad, width, prev, prev_min, cur, cur_min


@nb.njit(nogil=True, cache=True, inline="always")
def _step_fast(c, prev, o0, prev_min, P1, P2, out, pad, ob, n):
    """:func:`_step` on one cell's (NaN-filled) costs ``c``; ``o0 = pad + shift``.

    All in float32, as :func:`_step`: the path costs are computed in one
    vectorised loop (``ob``: float32 scratch), their minimum in a second
    one with four running minima (exact in any order)."""
    pv = prev[o0 - 1 : o0 + n + 1]
    ot = out[pad : pad + n]
    for k in range(n):
        o = _path_cost(c[k], pv[k], pv[k + 1], pv[k + 2], P1, P2, prev_min)
        ob[k] = o
        ot[k] = o
    return _min4(ob, n)


@nb.njit(nogil=True, cache=True, inline="always")
def _path_cost(c, below, at, above, P1, P2, prev_min):
    """A candidate's path cost (float32) from its cost ``c`` and the
    neighbour's path costs one label below, at and above its label."""
    m = min(at, min(below, above) + P1) - prev_min
    return c + min(m, P2)


@nb.njit(nogil=True, cache=True, inline="always")
def _label(prev, pad, nd, l):
    # a neighbour's path cost at its candidate l; +inf outside 0..nd-1
    return prev[pad + l] if 0 <= l < nd else _INF


@nb.njit(nogil=True, cache=True, inline="always")
def _step_bounded(c, prev, shift, prev_min, P1, P2, out, pad, ob, n, nd):
    """:func:`_step_fast` for a shift beyond the guard: the neighbour's
    costs read with bounds, the same arithmetic and values."""
    ot = out[pad : pad + n]
    for k in range(n):
        l = shift + k
        o = _path_cost(c[k], _label(prev, pad, nd, l - 1), _label(prev, pad, nd, l), _label(prev, pad, nd, l + 1),
                       P1, P2, prev_min)
        ob[k] = o
        ot[k] = o
    return _min4(ob, n)


@nb.njit(nogil=True, cache=True, inline="always")
def _min4(ob, n):
    if n <= 0:
        return _INF
    b0 = ob[0]
    b1 = b0
    b2 = b0
    b3 = b0
    k = 0
    while k + 4 <= n:
        b0 = min(b0, ob[k])
        b1 = min(b1, ob[k + 1])
        b2 = min(b2, ob[k + 2])
        b3 = min(b3, ob[k + 3])
        k += 4
    while k < n:
        b0 = min(b0, ob[k])
        k += 1
    return min(min(b0, b1), min(b2, b3))


@nb.njit(nogil=True, cache=True, inline="always")
def _min_lanes(ob):
    b = ob[0]
    for k in range(1, _LANES):
        b = min(b, ob[k])
    return b


@nb.njit(nogil=True, cache=True, inline="always")
def _absent(out, pad, n, nd):
    # candidates a cell does not have: +inf, as outside the slot
    for k in range(pad + n, pad + nd):
        out[k] = _INF


@nb.njit(nogil=True, cache=True, inline="always")
def _init_lanes(c, out, pad, ob, n):
    """A path's first cell, ``n <= _LANES``: its own costs, +inf for the
    other lanes; returns their minimum."""
    ot = out[pad : pad + _LANES]
    for k in range(_LANES):
        o = c[k] if k < n else _INF
        ob[k] = o
        ot[k] = o
    return _min_lanes(ob)


@nb.njit(nogil=True, cache=True, inline="always")
def _step_lanes(c, prev, o0, prev_min, P1, P2, out, pad, ob, n):
    """:func:`_step_fast` for ``n <= _LANES`` over a constant ``_LANES``
    lanes (+inf beyond ``n``): the same arithmetic and values."""
    pv = prev[o0 - 1 : o0 + _LANES + 1]
    ot = out[pad : pad + _LANES]
    for k in range(_LANES):
        o = _path_cost(c[k], pv[k], pv[k + 1], pv[k + 2], P1, P2, prev_min)
        o = o if k < n else _INF
        ob[k] = o
        ot[k] = o
    return _min_lanes(ob)


@nb.njit(nogil=True, cache=True, inline="always")
def _cell(c, prev, shift, prev_min, P1, P2, out, pad, ob, n, nd, wide, slot, first):
    """Path cost of one cell into slot ``out`` (its minimum returned,
    float32): a restart (``first``, its own costs) or :func:`_step` from
    the neighbour's slot ``prev`` whose labels are ``shift`` lower.

    ``wide[slot]`` says whether the slot holds more than ``_LANES``
    candidates: a fixed-lane update clears only its lanes."""
    lanes = n <= _LANES
    if lanes:
        if wide[slot]:
            _absent(out, pad, _LANES, nd)
            wide[slot] = False
    else:
        wide[slot] = True
    if first:
        if lanes:
            return _init_lanes(c, out, pad, ob, n)
        ot = out[pad : pad + n]
        for k in range(n):
            ot[k] = c[k]
            ob[k] = c[k]
        _absent(out, pad, n, nd)
        return _min4(ob, n)
    if -_GUARD <= shift <= _GUARD:
        if lanes:
            return _step_lanes(c, prev, pad + shift, prev_min, P1, P2, out, pad, ob, n)
        _absent(out, pad, n, nd)
        return _step_fast(c, prev, pad + shift, prev_min, P1, P2, out, pad, ob, n)
    # beyond the guard (beyond the neighbour's candidates too: then every
    # read is +inf and only the P2 transition remains, as in _step)
    _absent(out, pad, n, nd)
    return _step_bounded(c, prev, shift, prev_min, P1, P2, out, pad, ob, n, nd)


@nb.njit(nogil=True, cache=True)
def _fill_row(cost, i, value, nvalid, out):
    # only a cell's own candidates: the passes never read the others
    nd = cost.shape[2]
    for j in range(out.shape[0]):
        src = cost[i, j]
        dst = out[j]
        for k in range(min(nvalid[i, j], nd)):
            v = src[k]
            dst[k] = v if np.isfinite(v) else value
    return out


def _fast_scratch(nx: int, nd: int) -> tuple:
    """The buffers of :func:`_pass_fast`: path slots of the in-row and the
    row-crossing paths (:func:`_fast_buffers`), a row of filled costs
    (finite beyond a cell's own: the fixed lanes read them, unused), two
    float32 per-cell scratches, and the slots' wide flags (see
    :func:`_cell`)."""
    pad, width, prev, prev_min, cur, cur_min = _fast_buffers(nx, nd)
    return (
        pad, prev, prev_min, cur, cur_min, np.full((nx, width), _INF, np.float32),
        np.zeros((nx, max(nd, _LANES)), np.float32), np.empty(max(nd, _LANES), np.float32), np.empty(nd, np.float32),
        np.zeros(nx, np.bool_), np.zeros((3, nx), np.bool_), np.zeros((3, nx), np.bool_),
    )


# without reference counting: see the head of this section
@nb.njit(nogil=True, cache=True, _nrt=False)
def _pass_fast(cost, base, nvalid, P1, P2, S, forward, gi0, gj0, period, invalid, winners, out, scratch):
    """:func:`_pass` without a guide, bit for bit: invalid costs filled row
    by row (no filled copy of the volume), short path slots
    (:func:`_fast_buffers`), the four paths of a row summed into ``S`` in
    one sweep, in the reference's order. With ``winners`` (the second
    pass), each cell's complete sums go to
    :func:`~tiledsm.match.winner.best_of_cell` (``out``) instead of ``S``."""
    ny, nx, nd = cost.shape
    sgn = 1 if forward else -1
    pad, prev, prev_min, cur, cur_min, inrow, crow, ob, srow, inwide, wide, wide_prev = scratch
    for t in range(ny):
        i = t if forward else ny - 1 - t
        pi = i - sgn
        _fill_row(cost, i, invalid, nvalid, crow)
        rmin = np.float32(0.0)  # float32, as in _pass
        for u in range(nx):
            j = u if forward else nx - 1 - u
            first = u == 0 or restarts(gj0 + j, sgn, period) or nvalid[i, j - sgn] == 0
            pj = j if first else j - sgn
            rmin = _cell(crow[j], inrow[pj], base[i, j] - base[i, pj], rmin, P1, P2, inrow[j], pad, ob,
                         nvalid[i, j], nd, inwide, j, first)
        row_restart = t == 0 or restarts(gi0 + i, sgn, period)
        for d in range(3):
            dx = d - 1
            for j in range(nx):
                pj = j - dx
                first = row_restart or pj < 0 or pj >= nx or (dx != 0 and restarts(gj0 + j, dx, period))
                first = first or nvalid[pi, pj] == 0
                shift = 0
                if first:
                    pj = j  # a slot of this row, not read (row pi may lie outside the volume)
                else:
                    shift = base[i, j] - base[pi, pj]
                cur_min[d, j] = _cell(crow[j], prev[d, pj], shift, prev_min[d, pj], P1, P2, cur[d, j], pad, ob,
                                      nvalid[i, j], nd, wide[d], j, first)
        for j in range(nx):
            s = S[i, j]
            a = inrow[j, pad : pad + nd]
            b0 = cur[0, j, pad : pad + nd]
            b1 = cur[1, j, pad : pad + nd]
            b2 = cur[2, j, pad : pad + nd]
            n = min(nvalid[i, j], nd)
            if winners:
                # the last pass: the cell's sums are complete; its winner now, S not written back
                for k in range(n):
                    srow[k] = s[k] + a[k] + b0[k] + b1[k] + b2[k]
                best_of_cell(srow, cost[i, j], n, out, i, j)
            else:
                # the first pass sums a cell's own candidates only; the
                # second (S returned) also the others, +inf as in _pass
                for k in range(n if forward else nd):
                    s[k] = s[k] + a[k] + b0[k] + b1[k] + b2[k]
        prev, cur = cur, prev
        prev_min, cur_min = cur_min, prev_min
        wide, wide_prev = wide_prev, wide
