"""The compiled CUDA kernels of :mod:`tiledsm.match.cuda_kernel` (numba's
CUDA target). Imported by that module when a GPU kernel is first used, so
CPU runs never import ``numba.cuda``; under ``NUMBA_ENABLE_CUDASIM=1`` the
same kernels run in numba's CUDA simulator (tests). Each kernel names the
CPU function whose arithmetic it repeats, in the same floating-point types
and order."""

import math

import numpy as np
from numba import config, cuda

from tiledsm.match.sampling import CUBIC_A
from tiledsm.match.sweep import MASKED_COST
from tiledsm.match.winner import ABSENT

f64 = np.float64
f32 = np.float32
#: +inf of the paths (tiledsm.match.winner.ABSENT)
inf = f32(ABSENT)
masked = f32(MASKED_COST)
#: Keys' parameter
a = CUBIC_A

dev = cuda.jit(device=True, inline=True)

# Products are rounded on their own (libdevice's _rn multiplications): the
# compiler would otherwise fuse a product and the sum after it into one
# multiply-add, rounded once, which the CPU kernel never does. With them
# the GPU's samples and costs are the CPU kernel's bit for bit. The
# simulator runs plain Python products (the same values).
if config.ENABLE_CUDASIM:
    def mul(x, y):
        return x * y

    mul32 = mul
else:
    from numba.cuda import libdevice

    @dev
    def mul(x, y):
        """``x * y`` in float64, never fused with an addition."""
        return libdevice.dmul_rn(x, y)

    @dev
    def mul32(x, y):
        """``x * y`` in float32, never fused with an addition."""
        return libdevice.fmul_rn(x, y)


# The lattice lookups of tiledsm.match.sampling, with math.floor: numba's
# CUDA target has no numpy.floor (the CPU functions cannot be reused).
@dev
def lattice_cell(g, stride, n0, n):
    # tiledsm.match.sampling.lattice_cell
    u = g / stride
    k = int(math.floor(u))
    f = u - k
    k -= n0
    if k > n - 2:
        k = n - 2
        f = u - (k + n0)
    return k, f


@dev
def lattice_segment(tt, k0, nh):
    # tiledsm.match.sampling.lattice_segment
    kt = int(math.floor(tt))
    ft = tt - kt
    t0 = kt - k0
    if t0 < 0:
        t0 = 0
        ft = tt - k0
    elif t0 > nh - 2:
        t0 = nh - 2
        ft = tt - (k0 + t0)
    return t0, ft


@dev
def item(t, nx, depth):
    """Cell ``(i, j)`` and item ``k`` of flat thread index ``t`` over a
    ``(ny, nx, depth)`` layout (items fastest: neighbouring threads read
    neighbouring memory)."""
    k = t % depth
    cell = t // depth
    i = cell // nx
    return i, cell - i * nx, k


@dev
def bilinear(lat, v, t, i0, j0, w00, w01, w10, w11):
    # tiledsm.match.sweep._bilinear
    return (mul(w00, lat[v, t, i0, j0]) + mul(w01, lat[v, t, i0, j0 + 1]) + mul(w10, lat[v, t, i0 + 1, j0])
            + mul(w11, lat[v, t, i0 + 1, j0 + 1]))


# Keys' coefficients in float32 (tiledsm.match.sampling.cubic_weights)
one32 = f32(1.0)
a1 = f32(a)
a2 = f32(a + 2.0)


@dev
def cubic_weights(t):
    # tiledsm.match.sampling.cubic_weights, float32 t
    g = one32 - t
    return (mul32(mul32(a1, t), mul32(g, g)), mul32(g, (one32 + t) - mul32(mul32(a2, t), t)),
            mul32(t, (one32 + g) - mul32(mul32(a2, g), g)), mul32(mul32(a1, g), mul32(t, t)))


@dev
def column4(img, v, iy, c, w0, w1, w2, w3):
    # tiledsm.match.sampling.column4
    return ((mul32(w0, img[v, iy - 1, c]) + mul32(w1, img[v, iy, c])) + mul32(w2, img[v, iy + 1, c])
            + mul32(w3, img[v, iy + 2, c]))


@dev
def sample(img, v, h, w, y, x, cubic):
    """tiledsm.match.sampling.interpolate (bicubic: the arithmetic of
    tiledsm.match.sweep._bicubic_many)."""
    if math.isnan(y) or math.isnan(x) or math.isinf(y) or math.isinf(x):
        return f32(math.nan)
    if cubic:
        # floor(y) >= 1 and floor(y) + 2 < h, tested before flooring
        if not (y >= 1.0 and x >= 1.0 and y < h - 2.0 and x < w - 2.0):
            return f32(math.nan)
        iy = int(math.floor(y))
        ix = int(math.floor(x))
        # tiledsm.match.sampling.cubic_weights and cubic_sum, float32
        fy = f32(y - iy)
        fx = f32(x - ix)
        wy0, wy1, wy2, wy3 = cubic_weights(fy)
        wx0, wx1, wx2, wx3 = cubic_weights(fx)
        c = ix - 1
        c0 = column4(img, v, iy, c, wy0, wy1, wy2, wy3)
        c1 = column4(img, v, iy, c + 1, wy0, wy1, wy2, wy3)
        c2 = column4(img, v, iy, c + 2, wy0, wy1, wy2, wy3)
        c3 = column4(img, v, iy, c + 3, wy0, wy1, wy2, wy3)
        return (mul32(wx0, c0) + mul32(wx2, c2)) + (mul32(wx1, c1) + mul32(wx3, c3))
    if not (y >= 0.0 and x >= 0.0 and y < h - 1.0 and x < w - 1.0):
        return f32(math.nan)
    iy = int(math.floor(y))
    ix = int(math.floor(x))
    fy = y - iy
    fx = x - ix
    top = f64(img[v, iy, ix]) + mul(fx, f64(img[v, iy, ix + 1] - img[v, iy, ix]))
    bot = f64(img[v, iy + 1, ix]) + mul(fx, f64(img[v, iy + 1, ix + 1] - img[v, iy + 1, ix]))
    return f32(top + mul(fy, bot - top))


@cuda.jit(cache=True)
def sample_kernel(imgs, shapes, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c,
                  cubic, lo, hi, out):
    """``out[v, i, j, k]``: view ``v``'s sample of cell ``[i, j]`` at
    label ``lo[i, j] + k`` (tiledsm.match.sweep._sample_row)."""
    ny, nx = href.shape
    t = cuda.grid(1)
    if t >= ny * nx * out.shape[3]:
        return
    i, j, k = item(t, nx, out.shape[3])
    if lo[i, j] + k > hi[i, j]:
        return
    nh = lat_r.shape[1]
    gy = lat_r.shape[2]
    gx = lat_r.shape[3]
    i0, fy = lattice_cell(gi0 + i, stride, n0i, gy)
    j0, fx = lattice_cell(gj0 + j, stride, n0j, gx)
    w00 = mul(1 - fy, 1 - fx)
    w01 = mul(1 - fy, fx)
    w10 = mul(fy, 1 - fx)
    w11 = mul(fy, fx)
    tt = (href[i, j] + mul(f64(lo[i, j] + k), step)) / dh
    t0, ft = lattice_segment(tt, k0, nh)
    for v in range(out.shape[0]):
        ar = bilinear(lat_r, v, t0, i0, j0, w00, w01, w10, w11)
        br = bilinear(lat_r, v, t0 + 1, i0, j0, w00, w01, w10, w11)
        ac = bilinear(lat_c, v, t0, i0, j0, w00, w01, w10, w11)
        bc = bilinear(lat_c, v, t0 + 1, i0, j0, w00, w01, w10, w11)
        y = ar + mul(ft, br - ar) - win_r[v]
        x = ac + mul(ft, bc - ac) - win_c[v]
        out[v, i, j, k] = sample(imgs, v, shapes[v, 0], shapes[v, 1], y, x, cubic)


@dev
def zncc(s_a, s_b, s_aa, s_bb, s_ab, inv_n, eps):
    # tiledsm.match.zncc_rows._zncc
    va = s_aa - mul(mul(s_a, s_a), inv_n)
    vb = s_bb - mul(mul(s_b, s_b), inv_n)
    prod = va * vb
    if not prod > 0.0:
        # a flat or nodata window (the CPU kernel's IEEE division gives
        # a non-finite c there, rejected below)
        return f32(math.nan)
    c = (s_ab - mul(mul(s_a, s_b), inv_n)) / math.sqrt(prod)
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    if va > eps * (1.0 + s_aa) and vb > eps * (1.0 + s_bb) and c == c:
        return f32(1.0 - c)
    return f32(math.nan)


@dev
def pair_zncc(samp, u, w, lo, i, j, half, label, inv_n, eps):
    """``1 - ZNCC`` of views ``u`` and ``w`` over the window of cell ``[i,
    j]`` at ``label``: column sums of the rows top to bottom, then the
    columns left to right (tiledsm.match.zncc_rows: _column_sums, zncc_row)."""
    sa = 0.0
    sb = 0.0
    saa = 0.0
    sbb = 0.0
    sab = 0.0
    for c in range(j - half, j + half + 1):
        c0 = 0.0
        c1 = 0.0
        c00 = 0.0
        c11 = 0.0
        c01 = 0.0
        for r in range(i - half, i + half + 1):
            off = label - lo[r, c]
            x = f64(samp[u, r, c, off])
            y = f64(samp[w, r, c, off])
            c0 += x
            c00 += mul(x, x)
            c1 += y
            c11 += mul(y, y)
            c01 += mul(x, y)
        sa += c0
        sb += c1
        saa += c00
        sbb += c11
        sab += c01
    return zncc(sa, sb, saa, sbb, sab, inv_n, eps)


@cuda.jit(cache=True)
def zncc_kernel(samp, lo, base, nvalid, half, pair_u, pair_v, pair_w, eps, vol):
    """``vol[i, j, k]`` of the cells whose window lies in the block
    (tiledsm.match.zncc_rows.zncc_row): one pair's cost, or the pairs'
    weighted mean with three or more views."""
    ny, nx, nd = vol.shape
    t = cuda.grid(1)
    if t >= ny * nx * nd:
        return
    i, j, k = item(t, nx, nd)
    if k >= nvalid[i, j] or i < half or i >= ny - half or j < half or j >= nx - half:
        return
    wsz = 2 * half + 1
    inv_n = 1.0 / (wsz * wsz)
    label = base[i, j] + k
    if samp.shape[0] == 2:
        vol[i, j, k] = pair_zncc(samp, 0, 1, lo, i, j, half, label, inv_n, eps)
        return
    # weighted in float32, as the compiled kernel's totals
    tot = f32(0.0)
    cnt = f32(0.0)
    for p in range(pair_u.shape[0]):
        cst = pair_zncc(samp, pair_u[p], pair_v[p], lo, i, j, half, label, inv_n, eps)
        if cst == cst:
            tot += mul32(pair_w[p], cst)
            cnt += pair_w[p]
    vol[i, j, k] = tot / cnt if cnt != 0 else f32(math.nan)


@cuda.jit(cache=True)
def fill_kernel(nvalid, vol):
    """NaN for a cell's candidates (invalid until scored), MASKED_COST
    beyond (tiledsm.match.sweep.empty_volume)."""
    ny, nx, nd = vol.shape
    t = cuda.grid(1)
    if t >= ny * nx * nd:
        return
    i, j, k = item(t, nx, nd)
    vol[i, j, k] = f32(math.nan) if k < nvalid[i, j] else masked


@dev
def smaller(x, y):
    """``min(x, y)`` (numba's CUDA target lacks the two-argument builtin
    here); Python's choice of the first on ties."""
    return y if y < x else x


@dev
def restarts(g, sgn, period):
    # tiledsm.match.paths.restarts
    if period <= 0:
        return False
    if sgn > 0:
        return g % period == 0
    return (g + 1) % period == 0


@dev
def label_cost(buf, line, slot, l, n):
    # a predecessor's path cost at its candidate l; +inf outside 0..n-1
    return buf[line, slot, l] if 0 <= l < n else inf


@cuda.jit(cache=True)
def path_kernel(cost, base, nvalid, P1, P2, invalid, di, dj, gi0, gj0, period, assign, S, buf):
    """One path line per block: its cells in order, the candidates of
    a cell spread over the block's threads (tiledsm.match.paths._cell: path
    costs, transitions and the predecessor's minimum in float32). The path costs
    are added to ``S``, or written with ``assign`` (the first direction:
    ``0 + x`` is ``x``, so ``S`` needs no zeroing first)."""
    ny, nx, nd = cost.shape
    line = cuda.blockIdx.x
    tid = cuda.threadIdx.x
    nthreads = cuda.blockDim.x
    red = cuda.shared.array(1024, dtype=np.float32)
    # the line's first cell: the one whose predecessor leaves the block
    if di == 0:
        i = line
        j = 0 if dj > 0 else nx - 1
    elif dj == 0:
        i = 0 if di > 0 else ny - 1
        j = line
    elif line < nx:
        i = 0 if di > 0 else ny - 1
        j = line
    else:
        i = (0 if di > 0 else ny - 1) + di * (line - nx + 1)
        j = 0 if dj > 0 else nx - 1
    slot = 0
    prev_min = f32(0.0)
    first_cell = True
    while i >= 0 and i < ny and j >= 0 and j < nx:
        n = nvalid[i, j]
        if n > nd:
            n = nd
        pi = i - di
        pj = j - dj
        first = first_cell
        if not first:
            first = (di != 0 and restarts(gi0 + i, di, period)) or (dj != 0 and restarts(gj0 + j, dj, period))
            first = first or nvalid[pi, pj] == 0
        nq = 0
        shift = 0
        if not first:
            nq = nvalid[pi, pj]
            if nq > nd:
                nq = nd
            shift = base[i, j] - base[pi, pj]
        m = inf
        k = tid
        while k < n:
            c = cost[i, j, k]
            if math.isnan(c) or math.isinf(c):
                c = invalid
            if first:
                o = c
            else:
                l = shift + k
                below = label_cost(buf, line, slot, l - 1, nq)
                at = label_cost(buf, line, slot, l, nq)
                above = label_cost(buf, line, slot, l + 1, nq)
                side = smaller(below, above) + P1
                tr = smaller(at, side) - prev_min
                o = c + smaller(tr, P2)
            buf[line, 1 - slot, k] = o
            if assign:
                S[i, j, k] = o
            else:
                S[i, j, k] += o
            if o < m:
                m = o
            k += nthreads
        # the block's minimum of the cell's path costs
        red[tid] = m
        cuda.syncthreads()
        s = nthreads // 2
        while s > 0:
            if tid < s and red[tid + s] < red[tid]:
                red[tid] = red[tid + s]
            cuda.syncthreads()
            s //= 2
        m = red[0]
        if n <= 0:
            m = inf
        prev_min = m
        cuda.syncthreads()  # red[0] read by all before the next cell writes it
        slot = 1 - slot
        first_cell = False
        i += di
        j += dj


@cuda.jit(cache=True)
def winner_kernel(S, cost, nvalid, index, smin, ratio, cbest):
    """tiledsm.match.winner.best_of_cell, one thread per cell."""
    ny, nx, nd = S.shape
    t = cuda.grid(1)
    if t >= ny * nx:
        return
    i = t // nx
    j = t - i * nx
    n = smaller(nvalid[i, j], nd)
    kb = -1
    bst = inf
    for k in range(n):
        v = S[i, j, k]
        if v < bst:
            bst = v
            kb = k
    if kb < 0:
        index[i, j] = math.nan
        smin[i, j] = math.nan
        ratio[i, j] = math.nan
        cbest[i, j] = math.nan
        return
    second = inf
    for k in range(n):
        if k < kb - 1 or k > kb + 1:
            v = S[i, j, k]
            if v < second:
                second = v
    off = 0.0
    if 0 < kb < n - 1:
        lo_ = S[i, j, kb - 1]
        hi_ = S[i, j, kb + 1]
        # float64 as numba types best_of_cell's arithmetic (explicit: the
        # simulator's numpy scalars would keep float32)
        den = f64(lo_) - mul(2.0, f64(bst)) + f64(hi_)
        if den > 0:
            off = 0.5 * f64(lo_ - hi_) / den
    index[i, j] = kb + off
    smin[i, j] = bst
    ratio[i, j] = bst / second if second < inf and second > 0 else f32(0.0)
    cbest[i, j] = cost[i, j, kb]
