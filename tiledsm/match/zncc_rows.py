"""The windowed ZNCC of the compiled sweep (:mod:`tiledsm.match.sweep`),
one ground row at a time, from the samples of the rows its windows span.

Column sums over the window's rows are computed once per (column, label)
of a ground row and reused by the ``2 * half + 1`` cells whose windows
hold that column; each cell's window sums are added in the fixed order of
:func:`tiledsm.match.cost.zncc_cost` (columns left to right, rows top to
bottom, from 0; never running totals), so a cell's cost does not depend
on the block it is computed in. A pair's narrow bands (at most
:data:`NARROW` labels, a 5 x 5 window) take one loop per column and cell
over the labels, the same additions in the same order.

Conventions are those of :mod:`tiledsm.match.sweep`.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["NARROW", "row_hull", "zncc_row"]


@nb.njit(nogil=True, cache=True, inline="always")
def row_hull(base, nvalid, i, half, lo, hi):
    """``lo[c]``, ``hi[c]``: lowest first and highest last label of the
    searched cells ``[i, j]`` of block row ``i`` whose window columns
    ``j - half .. j + half`` hold column ``c`` and lie inside the block
    (columns without one are left as they are)."""
    nx = base.shape[1]
    for j in range(half, nx - half):
        if nvalid[i, j] <= 0:
            continue
        b = base[i, j]
        t = b + nvalid[i, j] - 1
        for c in range(j - half, j + half + 1):
            lo[c] = min(lo[c], b)
            hi[c] = max(hi[c], t)


@nb.njit(nogil=True, cache=True, inline="always")
def _column_sums(ring, i, half, c, cb, m, lo, pair_u, pair_v, out):
    """``out[q, k]``: sums over the rows ``i - half .. i + half`` (in that
    order) of column ``c`` at label ``cb + k``, ``k < m``, of the samples
    of each view (``q = v``), their squares (``nv + v``) and the products
    of each view pair (``2 nv + p``). Loops over ``k`` on 1-D slices with a
    non-negative index: they vectorise."""
    if m <= 0:
        return
    nv = ring.shape[0]
    wsz = ring.shape[1]
    if nv == 2 and wsz == 5 and m <= NARROW:
        _pair_column5(ring, i, c, cb, m, lo, out)
        return
    for q in range(out.shape[0]):
        out[q, :m] = 0.0
    if nv == 2:
        # a pair: each row's two samples read once for all five sums (the
        # same additions in the same order as below)
        s0, s1, s00, s11, s01 = out[0, :m], out[1, :m], out[2, :m], out[3, :m], out[4, :m]
        for r in range(i - half, i + half + 1):
            slot = r % wsz
            off = cb - lo[r, c]
            u = ring[0, slot, c, off : off + m]
            w = ring[1, slot, c, off : off + m]
            for k in range(m):
                x = np.float64(u[k])
                y = np.float64(w[k])
                s0[k] += x
                s00[k] += x * x
                s1[k] += y
                s11[k] += y * y
                s01[k] += x * y
        return
    for r in range(i - half, i + half + 1):
        slot = r % wsz
        off = cb - lo[r, c]
        for v in range(nv):
            src = ring[v, slot, c, off : off + m]
            d1 = out[v, :m]
            d2 = out[nv + v, :m]
            for k in range(m):
                x = np.float64(src[k])
                d1[k] += x
                d2[k] += x * x
        for p in range(pair_u.shape[0]):
            su = ring[pair_u[p], slot, c, off : off + m]
            sv = ring[pair_v[p], slot, c, off : off + m]
            d = out[2 * nv + p, :m]
            for k in range(m):
                d[k] += np.float64(su[k]) * np.float64(sv[k])


#: labels up to which a band is narrow: a pair's sums take the one-loop paths
#: (_pair_column5, _pair_cell5; wider bands vectorise better one quantity at
#: a time), and the sweep samples such cells in batches (sweep._sample_row)
NARROW = 32


@nb.njit(nogil=True, cache=True, inline="always")
def _pair_column5(ring, i, c, cb, m, lo, out):
    """:func:`_column_sums` of a pair and a 5-row window in one loop over
    the labels: each sum's five rows added top to bottom from 0, as there
    (one loop instead of five: a narrow band's ~10 labels leave the loops
    of a row too short to vectorise well)."""
    wsz = ring.shape[1]
    o0 = cb - lo[i - 2, c]
    o1 = cb - lo[i - 1, c]
    o2 = cb - lo[i, c]
    o3 = cb - lo[i + 1, c]
    o4 = cb - lo[i + 2, c]
    u0 = ring[0, (i - 2) % wsz, c]
    u1 = ring[0, (i - 1) % wsz, c]
    u2 = ring[0, i % wsz, c]
    u3 = ring[0, (i + 1) % wsz, c]
    u4 = ring[0, (i + 2) % wsz, c]
    w0 = ring[1, (i - 2) % wsz, c]
    w1 = ring[1, (i - 1) % wsz, c]
    w2 = ring[1, i % wsz, c]
    w3 = ring[1, (i + 1) % wsz, c]
    w4 = ring[1, (i + 2) % wsz, c]
    s0, s1, s00, s11, s01 = out[0], out[1], out[2], out[3], out[4]
    for k in range(m):
        x0 = np.float64(u0[o0 + k])
        x1 = np.float64(u1[o1 + k])
        x2 = np.float64(u2[o2 + k])
        x3 = np.float64(u3[o3 + k])
        x4 = np.float64(u4[o4 + k])
        y0 = np.float64(w0[o0 + k])
        y1 = np.float64(w1[o1 + k])
        y2 = np.float64(w2[o2 + k])
        y3 = np.float64(w3[o3 + k])
        y4 = np.float64(w4[o4 + k])
        s0[k] = ((((0.0 + x0) + x1) + x2) + x3) + x4
        s00[k] = ((((0.0 + x0 * x0) + x1 * x1) + x2 * x2) + x3 * x3) + x4 * x4
        s1[k] = ((((0.0 + y0) + y1) + y2) + y3) + y4
        s11[k] = ((((0.0 + y0 * y0) + y1 * y1) + y2 * y2) + y3 * y3) + y4 * y4
        s01[k] = ((((0.0 + x0 * y0) + x1 * y1) + x2 * y2) + x3 * y3) + x4 * y4


@nb.njit(nogil=True, cache=True, inline="always")
def _pair_cell5(col, cb, j, b, m, inv_n, eps, out):
    """A pair's costs of one cell, 5-column window: the window sums of
    :func:`zncc_row` (columns left to right from 0) and :func:`_zncc`,
    all in one loop over the cell's ``m`` labels (``out[:m]``)."""
    wsz = col.shape[0]
    o0 = b - cb[j - 2]
    o1 = b - cb[j - 1]
    o2 = b - cb[j]
    o3 = b - cb[j + 1]
    o4 = b - cb[j + 2]
    c0 = col[(j - 2) % wsz]
    c1 = col[(j - 1) % wsz]
    c2 = col[j % wsz]
    c3 = col[(j + 1) % wsz]
    c4 = col[(j + 2) % wsz]
    for k in range(m):
        sa = ((((0.0 + c0[0, o0 + k]) + c1[0, o1 + k]) + c2[0, o2 + k]) + c3[0, o3 + k]) + c4[0, o4 + k]
        sb = ((((0.0 + c0[1, o0 + k]) + c1[1, o1 + k]) + c2[1, o2 + k]) + c3[1, o3 + k]) + c4[1, o4 + k]
        saa = ((((0.0 + c0[2, o0 + k]) + c1[2, o1 + k]) + c2[2, o2 + k]) + c3[2, o3 + k]) + c4[2, o4 + k]
        sbb = ((((0.0 + c0[3, o0 + k]) + c1[3, o1 + k]) + c2[3, o2 + k]) + c3[3, o3 + k]) + c4[3, o4 + k]
        sab = ((((0.0 + c0[4, o0 + k]) + c1[4, o1 + k]) + c2[4, o2 + k]) + c3[4, o3 + k]) + c4[4, o4 + k]
        out[k] = _zncc(sa, sb, saa, sbb, sab, inv_n, eps)


# error_model="numpy": IEEE division. A flat window (not nodata: a constant
# patch) has a zero deviation; its NaN is turned into an invalid cost by
# _zncc's select, where numba's default Python model raised
# ZeroDivisionError (and kept a branch in every division of the loop).
# _nrt=False: it allocates nothing (its scratch is the caller's), and its
# many short array views then cost no reference counts (see sweep._sample_row).
@nb.njit(nogil=True, cache=True, error_model="numpy", _nrt=False)
def zncc_row(ring, i, half, lo, base, nvalid, pair_u, pair_v, pair_w, eps, vol, cb, ct, col, win, total, count):
    """Costs of the cells of block row ``i`` (all their labels) from the
    samples of rows ``i - half .. i + half`` in ``ring`` (``(nv, 2 half +
    1, nx, ns)``, row ``r`` in slot ``r % (2 half + 1)``, label ``lo[r, j]
    + k`` at ``[.., j, k]``). Scratch: ``cb, ct`` ``(nx,)`` int64, ``col``
    ``(2 half + 1, nq, ns)`` float64 (``nq = 2 nv + pairs``), ``win``
    ``(nq, nd)`` float64, ``total, count`` ``(nd,)`` float32."""
    nv = ring.shape[0]
    wsz = ring.shape[1]
    nx = ring.shape[2]
    ny = base.shape[0]
    npairs = pair_u.shape[0]
    inv_n = 1.0 / (wsz * wsz)
    if i < half or i >= ny - half:
        return
    # label range of each column's sums: the cells of this row whose window holds it
    big = np.int64(1) << 60
    for c in range(nx):
        cb[c] = big
        ct[c] = -big
    row_hull(base, nvalid, i, half, cb, ct)
    ncs = 0
    for c in range(nx):
        ncs = max(ncs, ct[c] - cb[c] + 1)
    if ncs <= 0:
        return
    nq = 2 * nv + npairs
    # column sums over the window's rows (top to bottom), per quantity:
    # S_v, S_vv, S_uv, in col; made as the window moves right and kept for
    # the 2 half + 1 columns it spans (a few kB: they stay in cache)
    made = 0
    for j in range(half, nx - half):
        while made <= j + half:
            _column_sums(ring, i, half, made, cb[made], ct[made] - cb[made] + 1, lo, pair_u, pair_v, col[made % wsz])
            made += 1
        m = nvalid[i, j]
        if m <= 0:
            continue
        b = base[i, j]
        if npairs == 1 and wsz == 5 and m <= NARROW:
            _pair_cell5(col, cb, j, b, m, inv_n, eps, vol[i, j])
            continue
        # window sums in the order of cost.zncc_cost: columns left to right
        # (each quantity's; the column's ring slot found once for all)
        for q in range(nq):
            w = win[q, :m]
            for k in range(m):
                w[k] = 0.0
        for c in range(j - half, j + half + 1):
            off = b - cb[c]
            cs = col[c % wsz]
            for q in range(nq):
                w = win[q, :m]
                src = cs[q, off : off + m]
                for k in range(m):
                    w[k] += src[k]
        out = vol[i, j, :m]
        if npairs == 1:
            sa, sb, saa, sbb, sab = win[0, :m], win[1, :m], win[2, :m], win[3, :m], win[4, :m]
            for k in range(m):
                out[k] = _zncc(sa[k], sb[k], saa[k], sbb[k], sab[k], inv_n, eps)
            continue
        tot = total[:m]
        cnt = count[:m]
        for k in range(m):
            tot[k] = 0.0
            cnt[k] = 0.0
        for p in range(npairs):
            u = pair_u[p]
            v = pair_v[p]
            wp = pair_w[p]
            sa, sb, saa, sbb, sab = win[u, :m], win[v, :m], win[nv + u, :m], win[nv + v, :m], win[2 * nv + p, :m]
            for k in range(m):
                cst = _zncc(sa[k], sb[k], saa[k], sbb[k], sab[k], inv_n, eps)
                if cst == cst:
                    tot[k] += wp * cst
                    cnt[k] += wp
        for k in range(m):
            out[k] = tot[k] / cnt[k] if cnt[k] != 0 else np.float32(np.nan)


@nb.njit(nogil=True, cache=True, inline="always")
def _zncc(s_a, s_b, s_aa, s_bb, s_ab, inv_n, eps):
    """``1 - ZNCC`` (float32) from window sums, the arithmetic of
    :func:`tiledsm.match.cost.zncc_cost`; NaN for a flat window or where a
    sum is not finite (the window touched nodata). Written with selects,
    not early returns, so that loops over candidates vectorise; the caller
    is compiled with IEEE division (a flat window divides by zero)."""
    va = s_aa - s_a * s_a * inv_n
    vb = s_bb - s_b * s_b * inv_n
    c = (s_ab - s_a * s_b * inv_n) / np.sqrt(va * vb)
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    good = (va > eps * (1.0 + s_aa)) & (vb > eps * (1.0 + s_bb)) & (c == c)
    return np.float32(1.0 - c) if good else np.float32(np.nan)
