"""The SGVLL cost volume with the candidate loop compiled: sampling along
each cell's vertical line and windowed ZNCC, one ground row at a time.

:func:`cost_volume` gives the volume :func:`tiledsm.match.sgvll.match_block`
scores, bit for bit the one of the plain sweep (one whole-block resampling
and ZNCC per candidate height, ``kernel="reference"``), in a fraction of
the time:

- **Only the candidates a cell needs are sampled.** Cell ``p`` is sampled
  at the labels of the cells whose ZNCC window contains it (the hull of
  their ranges), not at every label of the block's bounding box.
- **The projection is walked along the vertical line.** The image track of
  a ground cell is piecewise linear in height on the projection lattice's
  height nodes (:func:`tiledsm.match.sgvll.match_block`: exact RPC
  projections every ``proj_stride`` cells and ``lattice_steps`` height
  steps); the bilinear ground interpolation of the two nodes around the
  candidate is done once per lattice segment of the line, and each
  candidate costs one linear interpolation in height. The arithmetic is
  that of the trilinear lookup of the plain sweep, so the samples are
  identical.
- **ZNCC window sums are shared between cells**
  (:mod:`tiledsm.match.zncc_rows`). (Not between candidates:
  in object space every view's samples move with the candidate height, so
  no window sum serves two candidates.) Column sums over the window's rows
  are computed once per (column, label) of a ground row and reused by the
  ``2 * half + 1`` cells whose windows hold that column; the loops over
  labels are innermost and contiguous (vectorised). Each cell's window
  sums are still added in the fixed order of
  :func:`tiledsm.match.cost.zncc_cost` (never running totals), so a cell's
  cost does not depend on the block it is computed in.

Samples of the ``2 * half + 1`` rows a ground row's windows need live in a
ring buffer: memory beyond the cost volume is a few rows of samples.

Conventions are those of :mod:`tiledsm.match.sgvll`: candidate ``k`` of
cell ``[i, j]`` is the height ``href[i, j] + (base[i, j] + k) * step``;
``vol[i, j, k]`` is ``1 - ZNCC`` (two views) or ``1 -`` the weighted mean
ZNCC over view pairs (three or more), NaN when invalid (window touching
nodata or the block's border, flat window), :data:`MASKED_COST` for
``k >= nvalid[i, j]``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from tiledsm.match.sampling import cubic_sum, cubic_weights, interpolate, lattice_cell, lattice_segment
from tiledsm.match.zncc_rows import NARROW, row_hull, zncc_row

__all__ = ["MASKED_COST", "cost_volume", "empty_volume", "sample_hull", "sample_plan", "track", "view_pairs"]

#: cost of candidates that lie outside a cell's own height range (never chosen)
MASKED_COST = np.float32(4.0)


@nb.njit(nogil=True, cache=True)
def sample_hull(base, nvalid, half):
    """Labels at which each cell must be sampled: ``(lo, hi)`` int64 arrays,
    the hull of the label ranges ``[base, base + nvalid - 1]`` of the cells
    whose ``(2 half + 1)``-square window holds it and lies inside the block
    (the cells whose cost is computed); ``lo > hi`` where none."""
    ny, nx = base.shape
    big = np.int64(1) << 60
    lo_r = np.full((ny, nx), big, np.int64)
    hi_r = np.full((ny, nx), -big, np.int64)
    for i in range(half, ny - half):
        row_hull(base, nvalid, i, half, lo_r[i], hi_r[i])
    lo = np.full((ny, nx), big, np.int64)
    hi = np.full((ny, nx), -big, np.int64)
    for i in range(ny):
        for r in range(max(0, i - half), min(ny, i + half + 1)):
            for j in range(nx):
                if lo_r[r, j] < lo[i, j]:
                    lo[i, j] = lo_r[r, j]
                if hi_r[r, j] > hi[i, j]:
                    hi[i, j] = hi_r[r, j]
    return lo, hi


@nb.njit(nogil=True, cache=True, inline="always")
def _bilinear(lat, t, i0, j0, w00, w01, w10, w11):
    # the expression of sampling.trilinear, plane by plane
    return w00 * lat[t, i0, j0] + w01 * lat[t, i0, j0 + 1] + w10 * lat[t, i0 + 1, j0] + w11 * lat[t, i0 + 1, j0 + 1]


@nb.njit(nogil=True, cache=True, inline="always")
def _track(lat_r, lat_c, i0, j0, fy, fx, k0, dh, hr, step, l0, win_r, win_c, ys, xs):
    """Image positions ``(ys[k], xs[k])`` (window pixels, array-index
    convention) of one cell's vertical line at the heights ``hr + (l0 + k)
    * step``, ``k < len(ys)``: the cell's lattice interval ``(i0, j0)`` and
    fractions ``(fy, fx)`` (:func:`~tiledsm.match.sampling.lattice_cell`),
    height nodes ``(k0 + t) * dh``. The line is piecewise linear between
    height nodes: the bilinear ground interpolation of a segment's two
    ends is done once per segment, each candidate is one linear
    interpolation (the arithmetic of the trilinear lookup,
    :func:`~tiledsm.match.sampling.trilinear`)."""
    nh = lat_r.shape[0]
    w00 = (1 - fy) * (1 - fx)
    w01 = (1 - fy) * fx
    w10 = fy * (1 - fx)
    w11 = fy * fx
    # the heights in lattice steps first, in ys: one vectorised loop of
    # divisions (a quarter of the tracks' time when inside the next loop)
    for k in range(ys.shape[0]):
        ys[k] = (hr + (l0 + k) * step) / dh
    tcur = -1
    ar = 0.0
    br = 0.0
    ac = 0.0
    bc = 0.0
    for k in range(ys.shape[0]):
        t0, ft = lattice_segment(ys[k], k0, nh)
        if t0 != tcur:
            # a new lattice segment of the vertical line: its two ends
            ar = _bilinear(lat_r, t0, i0, j0, w00, w01, w10, w11)
            br = _bilinear(lat_r, t0 + 1, i0, j0, w00, w01, w10, w11)
            ac = _bilinear(lat_c, t0, i0, j0, w00, w01, w10, w11)
            bc = _bilinear(lat_c, t0 + 1, i0, j0, w00, w01, w10, w11)
            tcur = t0
        ys[k] = ar + ft * (br - ar) - win_r
        xs[k] = ac + ft * (bc - ac) - win_c


@nb.njit(nogil=True, cache=True, error_model="numpy")
def _track_many(lat_r, lat_c, stride, k0, dh, gi, gj, n0i, n0j, href, step, l0, ys, xs):
    nh, gy, gx = lat_r.shape
    for n in range(gi.shape[0]):
        i0, fy = lattice_cell(gi[n], stride, n0i, gy)
        j0, fx = lattice_cell(gj[n], stride, n0j, gx)
        _track(lat_r, lat_c, i0, j0, fy, fx, k0, dh, href[n], step, l0, 0.0, 0.0, ys[n], xs[n])


def track(lat_r, lat_c, stride, k0, dh, cells, nodes0, href, step, labels) -> tuple[np.ndarray, np.ndarray]:
    """Image positions of the vertical lines of ``cells`` as the sweep
    computes them (see :func:`cost_volume` for the lattice arguments).

    Parameters
    ----------
    cells : (numpy.ndarray, numpy.ndarray)
        Whole-grid row and column indices ``(n,)`` of the cells.
    href : numpy.ndarray
        ``(n,)`` reference heights, metres.
    labels : (int, int)
        First label and number of labels: heights ``href + label * step``.

    Returns
    -------
    rows, cols : numpy.ndarray
        ``(n, count)`` full-image positions in the array-index convention
        (GDAL's minus 0.5) of the lattice's image.
    """
    gi = np.asarray(cells[0], np.int64).ravel()
    gj = np.asarray(cells[1], np.int64).ravel()
    l0, count = int(labels[0]), int(labels[1])
    ys = np.empty((gi.size, count))
    xs = np.empty((gi.size, count))
    _track_many(np.ascontiguousarray(lat_r, np.float64), np.ascontiguousarray(lat_c, np.float64), int(stride),
                int(k0), float(dh), gi, gj, int(nodes0[0]), int(nodes0[1]),
                np.asarray(href, np.float64).ravel(), float(step), l0, ys, xs)
    return ys, xs


@nb.njit(nogil=True, cache=True, inline="always")
def _bicubic_many(img, ys, xs, out, iy, ix, wy, wx):
    """``out[k] = interpolate(img, ys[k], xs[k], cubic=True)`` for all ``k``,
    bit for bit (the arithmetic of :func:`~tiledsm.match.sampling.cubic_at`),
    in two loops: the pixels and kernel weights of every position first
    (``iy, ix``: ``(n,)`` int64, -1 where the support leaves the image;
    ``wy, wx``: ``(4, n)`` float32 scratch), then the 4 x 4 gathers. The first loop
    has no memory dependence and vectorises: 17 % less time on a coarsest
    task's cost volume, 5 % on a level-0 task's, than one loop doing both
    per sample (captured tasks of the 4096² scene)."""
    h, w = img.shape
    n = ys.shape[0]
    for k in range(n):
        y = ys[k]
        x = xs[k]
        y0 = np.floor(y)
        x0 = np.floor(x)
        # NaN positions fail these tests too
        inside = y0 >= 1.0 and x0 >= 1.0 and y0 + 2.0 < h and x0 + 2.0 < w
        wy[0, k], wy[1, k], wy[2, k], wy[3, k] = cubic_weights(y - y0)
        wx[0, k], wx[1, k], wx[2, k], wx[3, k] = cubic_weights(x - x0)
        iy[k] = int(y0) if inside else -1
        ix[k] = int(x0) if inside else -1
    for k in range(n):
        r = iy[k]
        if r < 0:
            out[k] = np.nan
            continue
        out[k] = cubic_sum(img, r, ix[k], wy[0, k], wy[1, k], wy[2, k], wy[3, k], wx[0, k], wx[1, k], wx[2, k], wx[3, k])


# The row kernels below and their driver (_sweep) are compiled without the
# runtime's reference counting (_nrt=False, as tiledsm.match.paths._pass_fast):
# they allocate nothing (_sweep_scratch does), and a narrow band's cells make
# many short array views (a dozen per cell and view), each an atomic
# increment and decrement with it.
@nb.njit(nogil=True, cache=True, error_model="numpy", _nrt=False)
def _sample_row(img, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c, cubic, r,
                lo, hi, out, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts):
    """Samples of one view at the cells of block row ``r``: ``out[j, k]``
    at label ``lo[r, j] + k`` for the labels ``lo[r, j]..hi[r, j]``
    (:func:`sample_hull`), at heights ``href[r, j] + label * step``.

    The lines of consecutive cells are tracked into one batch of positions
    (``yb, xb``, float64 ``(cap,)``, ``cap > ns``: batches fill the first
    ``cap - ns``) and
    interpolated together (:func:`_batch`; ``sb, iyb, ixb, wyb, wxb`` its
    scratch, ``cells, starts`` ``(nx,)`` int64 the batch's cells): a narrow
    band's ~10 labels per cell leave a cell's own loops too short to
    vectorise. A cell of more than ``NARROW`` labels is interpolated
    alone, straight into ``out`` (in the last ``m <= ns`` entries of the
    scratch, which a batch leaves free)."""
    _, gy, gx = lat_r.shape
    nx = href.shape[1]
    ns = out.shape[1]
    cap = yb.shape[0]
    i0, fy = lattice_cell(gi0 + r, stride, n0i, gy)
    pos = 0
    npend = 0
    for j in range(nx):
        l0 = lo[r, j]
        l1 = hi[r, j]
        if l1 < l0:
            continue
        m = l1 - l0 + 1
        j0, fx = lattice_cell(gj0 + j, stride, n0j, gx)
        if m > NARROW:
            # a wide band: its own loops are long enough, no copy
            _track(lat_r, lat_c, i0, j0, fy, fx, k0, dh, href[r, j], step, l0, win_r, win_c, yb[cap - m :],
                   xb[cap - m :])
            if cubic:
                _bicubic_many(img, yb[cap - m :], xb[cap - m :], out[j, :m], iyb, ixb, wyb, wxb)
            else:
                _batch(img, cubic, m, 0, yb[cap - m :], xb[cap - m :], out[j, :m], iyb, ixb, wyb, wxb, cells,
                       starts, out)
            continue
        if pos + m > cap - ns:
            _batch(img, cubic, pos, npend, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts, out)
            pos = 0
            npend = 0
        _track(lat_r, lat_c, i0, j0, fy, fx, k0, dh, href[r, j], step, l0, win_r, win_c, yb[pos : pos + m],
               xb[pos : pos + m])
        cells[npend] = j
        starts[npend] = pos
        npend += 1
        pos += m
    _batch(img, cubic, pos, npend, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts, out)


@nb.njit(nogil=True, cache=True, inline="always")
def _batch(img, cubic, n, ncells, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts, out):
    """Interpolate the batch's ``n`` positions ``yb, xb`` into ``sb``
    (bicubic: :func:`_bicubic_many`; else :func:`interpolate`), then copy
    cell ``cells[p]``'s samples (``sb[starts[p]:]``) to its row of ``out``."""
    if n <= 0:
        return
    h, w = img.shape
    if cubic:
        _bicubic_many(img, yb[:n], xb[:n], sb[:n], iyb, ixb, wyb, wxb)
    else:
        for k in range(n):
            sb[k] = interpolate(img, yb[k], xb[k], cubic, h, w)
    for p in range(ncells):
        a = starts[p]
        b = starts[p + 1] if p + 1 < ncells else n
        dst = out[cells[p]]
        for k in range(b - a):
            dst[k] = sb[a + k]


#: positions a row's sampling tracks before it interpolates them together
#: (_sample_row): cells' lines batched up to this many samples (a few tens
#: of kB of scratch, kept in the core's cache)
_BATCH = 512

@nb.njit(nogil=True, cache=True)
def empty_volume(nvalid, nd):
    """``(ny, nx, nd)`` float32: NaN (invalid until computed) for the
    candidates ``k < nvalid`` of each cell, :data:`MASKED_COST` beyond."""
    ny, nx = nvalid.shape
    vol = np.empty((ny, nx, nd), np.float32)
    nan = np.float32(np.nan)
    for i in range(ny):
        for j in range(nx):
            n = nvalid[i, j]
            v = vol[i, j]
            for k in range(nd):
                v[k] = nan if k < n else MASKED_COST
    return vol


def sample_plan(base, nvalid, half: int, details: dict | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """``(lo, hi, ns)``: the labels each cell is sampled at
    (:func:`sample_hull`) and the most of any cell; ``details``, if given,
    gets ``n_samples``, the (cell, label) samples per view."""
    lo, hi = sample_hull(base, nvalid, half)
    span = np.maximum(hi - lo + 1, 0)
    if details is not None:
        details["n_samples"] = int(span.sum())
    return lo, hi, int(span.max()) if span.size else 0


def view_pairs(nv: int, pair_w=None) -> tuple[list[tuple[int, int]], np.ndarray]:
    """The view pairs ``(u, v)``, ``u < v``, of ``nv`` views and their
    float32 weights (the upper triangle of ``pair_w``; ones without it)."""
    pairs = [(u, v) for u in range(nv) for v in range(u + 1, nv)]
    w = np.ones((nv, nv), np.float32) if pair_w is None else np.asarray(pair_w, np.float32)
    return pairs, np.array([w[u, v] for u, v in pairs], np.float32)


def cost_volume(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None, eps: float = 1e-6,
) -> np.ndarray:
    """The SGVLL cost volume of a block (see the module docstring).

    Parameters
    ----------
    imgs : list of numpy.ndarray
        One float32 image window per view (NaN nodata).
    lat_r, lat_c : numpy.ndarray
        ``(nv, nh, gy, gx)`` projection lattice of every view, array-index
        pixel convention of the full image (``row - 0.5``, ``col - 0.5``);
        ground nodes every ``stride`` cells of the whole grid from node
        ``nodes0 = (n0i, n0j)``, height nodes ``(k0 + t) * dh`` metres.
    href : numpy.ndarray
        ``(ny, nx)`` float64 reference surface, metres.
    step : float
        Height step, metres.
    origin : (int, int)
        Whole-grid index of block cell ``[0, 0]``.
    win_r, win_c : numpy.ndarray
        ``(nv,)`` window origin of each view in its full image, pixels.
    cubic : bool
        Bicubic (Keys, a = -0.75) or bilinear sampling.
    base, nvalid : numpy.ndarray
        ``(ny, nx)`` int64 first label and number of labels of each cell.
    half : int
        ZNCC half window, cells.
    pair_w : numpy.ndarray, optional
        ``(nv, nv)`` pair weights (upper triangle read), three or more views.
    details : dict, optional
        Filled with ``n_samples``: (cell, label) samples taken per view.
    eps : float
        Flat-window threshold of :func:`tiledsm.match.cost.zncc_cost`.

    Returns
    -------
    numpy.ndarray
        ``(ny, nx, nd)`` float32 cost volume, ``nd = nvalid.max()``.
    """
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(nvalid.max()))
    base = np.ascontiguousarray(base, np.int64)
    nvalid = np.ascontiguousarray(nvalid, np.int64)
    vol = empty_volume(nvalid, nd)
    lo, hi, ns = sample_plan(base, nvalid, half, details)
    if ns <= 0:
        return vol
    pairs, pw = view_pairs(nv, pair_w)
    pair_u = np.array([p[0] for p in pairs], np.int64)
    pair_v = np.array([p[1] for p in pairs], np.int64)
    wsz = 2 * half + 1
    ring = np.full((nv, wsz, nx, ns), np.nan, np.float32)
    _sweep(tuple(np.ascontiguousarray(im, np.float32) for im in imgs),
           np.ascontiguousarray(lat_r, np.float64), np.ascontiguousarray(lat_c, np.float64), int(stride), int(k0),
           float(dh), np.ascontiguousarray(href, np.float64), float(step), int(origin[0]), int(origin[1]),
           int(nodes0[0]), int(nodes0[1]), np.asarray(win_r, np.float64), np.asarray(win_c, np.float64), bool(cubic),
           lo, hi, base, nvalid, int(half), pair_u, pair_v, pw, float(eps), ring, vol,
           *_sweep_scratch(nv, len(pairs), nx, ns, nd, half))
    return vol


def _sweep_scratch(nv: int, npairs: int, nx: int, ns: int, nd: int, half: int) -> tuple:
    """The scratch of :func:`_sweep`: a line's positions, pixels and
    kernel weights (:func:`_sample_row`), then a row's column label ranges,
    column sums, window sums and pair totals (:func:`zncc_row`)."""
    nq = 2 * nv + npairs
    cap = ns + _BATCH
    return (np.empty(cap), np.empty(cap), np.empty(cap, np.float32), np.empty(cap, np.int64), np.empty(cap, np.int64),
            np.empty((4, cap), np.float32), np.empty((4, cap), np.float32), np.empty(nx, np.int64), np.empty(nx, np.int64),
            np.empty(nx, np.int64), np.empty(nx, np.int64), np.empty((2 * half + 1, nq, ns)),
            np.empty((nq, nd)), np.empty(nd, np.float32), np.empty(nd, np.float32))


@nb.njit(nogil=True, cache=True, error_model="numpy", _nrt=False)
def _sweep(imgs, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c, cubic, lo, hi, base,
           nvalid, half, pair_u, pair_v, pw, eps, ring, vol, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts, cb, ct, col,
           win, total, count):
    """The block's rows in turn: each view sampled into the ring's slot of
    row ``r`` (:func:`_sample_row`), then the costs of row ``r - half``
    (:func:`zncc_row`); one compiled call per block (a call per row and
    view cost each row a few dispatches). ``imgs``: a tuple of the views'
    float32 windows; the other arguments as :func:`cost_volume` and its
    scratch (:func:`_sweep_scratch`)."""
    ny = href.shape[0]
    wsz = 2 * half + 1
    for r in range(ny):
        slot = r % wsz
        for v in range(len(imgs)):
            _sample_row(imgs[v], lat_r[v], lat_c[v], stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r[v],
                        win_c[v], cubic, r, lo, hi, ring[v, slot], yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts)
        i = r - half
        if i >= half:
            zncc_row(ring, i, half, lo, base, nvalid, pair_u, pair_v, pw, eps, vol, cb, ct, col, win, total, count)
