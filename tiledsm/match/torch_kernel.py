"""The SGVLL matching kernel through torch: cost volume and semi-global
aggregation on any torch device (a CUDA GPU; the CPU for tests).

The same arithmetic as the compiled kernel (:mod:`tiledsm.match.sweep`,
:func:`tiledsm.match.sgm.aggregate` with ``fast=True``), written as whole
tensor operations instead of per-cell loops, in the same floating-point
types and order of operations (the products and sums of the sampling and
of the correlation windows in float64, samples and path costs stored in
float32), so that on the CPU it gives the compiled kernel's volume and
``S`` (checked in ``tests/match/test_torch_kernel.py``):

- **Sampling.** Each cell is sampled at the labels of its hull
  (:func:`~tiledsm.match.sweep.sample_hull`): image positions from the
  projection lattice (bilinear on the ground, linear in height, per
  candidate), then bicubic (Keys, a = -0.75) or bilinear interpolation by
  gathers of the 4 x 4 (2 x 2) support.
- **ZNCC.** The window sums of every cell and candidate are gathered from
  the neighbours' samples at the same absolute label: column sums (rows top
  to bottom), then the window (columns left to right), as
  :func:`tiledsm.match.cost.zncc_cost` adds them.
- **Aggregation.** The four paths of a sweep direction advance one row (or
  column) at a time over all cells of it and all their candidates; a
  neighbour's path costs are gathered at the label shift between the two
  cells' first candidates. Restart lines, gaps and absent candidates as in
  :func:`~tiledsm.match.sgm.aggregate`.

Winner-take-all and the masks stay on the CPU (:mod:`tiledsm.match.sgm`).
Selected by ``SGVLLParams(kernel="torch", device=...)`` (``tiledsm dsm
--device cuda``).
"""

from __future__ import annotations

import numpy as np

from tiledsm.match.sampling import CUBIC_A
from tiledsm.match.sweep import empty_volume, sample_plan, view_pairs

__all__ = ["aggregate", "check_device", "cost_volume"]

#: (cell, candidate) pairs a sampling or correlation step handles at once,
#: on the CPU and on another device: bounds the memory (a few dozen float64
#: arrays of this size: 0.2 GB on the CPU, 0.8 GB on a GPU, where fewer,
#: larger steps launch fewer kernels)
_PAIRS_PER_STEP = {"cpu": 1 << 20, "other": 1 << 22}


def _pairs_per_step(device) -> int:
    return _PAIRS_PER_STEP["cpu" if device.type == "cpu" else "other"]


def _torch():
    import torch

    return torch


def check_device(device: str) -> None:
    """Raise :class:`ValueError` naming ``device`` when torch cannot run on
    it (not a device name, no CUDA or MPS device, no such index)."""
    torch = _torch()
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device {device!r} is not a torch device ({exc})") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r}: torch {torch.__version__} sees no CUDA device here")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {device!r}: torch {torch.__version__} sees no MPS device here")
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device {device!r}: the torch kernel runs on cpu, cuda or mps devices")


def _lattice_cell(g, stride: int, n0: int, n: int):
    """:func:`tiledsm.match.sampling.lattice_cell` of integer tensor ``g``."""
    torch = _torch()
    u = g.double() / stride
    k = torch.floor(u)
    f = u - k
    k = k.long() - n0
    over = k > n - 2
    k = torch.where(over, torch.full_like(k, n - 2), k)
    f = torch.where(over, u - (k + n0).double(), f)
    return k, f


def _height_segment(h, dh: float, k0: int, nh: int):
    """:func:`tiledsm.match.sampling.height_segment` of float64 tensor ``h``."""
    torch = _torch()
    tt = h / dh
    kt = torch.floor(tt)
    ft = tt - kt
    t0 = kt.long() - k0
    low, high = t0 < 0, t0 > nh - 2
    ft = torch.where(low, tt - k0, ft)
    t0 = torch.where(low, torch.zeros_like(t0), t0)
    ft = torch.where(high, tt - (k0 + nh - 2), ft)
    t0 = torch.where(high, torch.full_like(t0, nh - 2), t0)
    return t0, ft


def _plane(lat, t, i0, j0, w00, w01, w10, w11):
    # sweep._bilinear: the four nodes summed in its order
    a = w00 * lat[t, i0, j0]
    a = a + w01 * lat[t, i0, j0 + 1]
    a = a + w10 * lat[t, i0 + 1, j0]
    return a + w11 * lat[t, i0 + 1, j0 + 1]


def _keys_near(d, a: float = CUBIC_A):
    return ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0


def _keys_far(d, a: float = CUBIC_A):
    return ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a


def _interpolate(img, y, x, cubic: bool):
    """``img`` (float32, ``h x w``) at float64 positions: the values of
    :func:`tiledsm.match.sampling.interpolate` (NaN where the support
    leaves the image or touches NaN), float64."""
    torch = _torch()
    h, w = img.shape
    fy0, fx0 = torch.floor(y), torch.floor(x)
    fy, fx = y - fy0, x - fx0
    if cubic:
        ok = (fy0 >= 1.0) & (fx0 >= 1.0) & (fy0 + 2.0 < h) & (fx0 + 2.0 < w)
        wx = (_keys_far(fx + 1.0), _keys_near(fx), _keys_near(1.0 - fx), _keys_far(2.0 - fx))
        wy = (_keys_far(fy + 1.0), _keys_near(fy), _keys_near(1.0 - fy), _keys_far(2.0 - fy))
        offsets = (-1, 0, 1, 2)
    else:
        ok = (fy0 >= 0.0) & (fx0 >= 0.0) & (fy0 + 1.0 < h) & (fx0 + 1.0 < w)
    r = torch.where(ok, fy0, torch.ones_like(fy0)).long()
    c = torch.where(ok, fx0, torch.ones_like(fx0)).long()
    flat = img.reshape(-1)
    nan = torch.full_like(y, float("nan"))
    if not cubic:
        # the differences of neighbouring pixels in float32, as interpolate has them
        p = r * w + c
        top = flat[p].double() + fx * (flat[p + 1] - flat[p]).double()
        bot = flat[p + w].double() + fx * (flat[p + w + 1] - flat[p + w]).double()
        return torch.where(ok, top + fy * (bot - top), nan)
    acc = torch.zeros_like(y)
    for wyi, dr in zip(wy, offsets):
        base = (r + dr) * w + c
        row = wx[0] * flat[base + offsets[0]].double()
        for wxi, dc in zip(wx[1:], offsets[1:]):
            row = row + wxi * flat[base + dc].double()
        acc = acc + wyi * row
    return torch.where(ok, acc, nan)


def _samples(img, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c, cubic, lo, ns):
    """``(ny, nx, ns)`` float32 samples of one view: cell ``[i, j]`` at the
    labels ``lo[i, j] + s`` (as :func:`tiledsm.match.sweep._sample_row`;
    labels beyond the cell's hull are sampled too and never read)."""
    torch = _torch()
    dev = img.device
    nh, gy, gx = lat_r.shape
    ny, nx = href.shape
    out = torch.empty((ny, nx, ns), dtype=torch.float32, device=dev)
    s = torch.arange(ns, device=dev)
    i0, fy = _lattice_cell(torch.arange(ny, device=dev) + gi0, stride, n0i, gy)
    j0, fx = _lattice_cell(torch.arange(nx, device=dev) + gj0, stride, n0j, gx)
    rows = max(1, _pairs_per_step(dev) // max(1, nx * ns))
    for a in range(0, ny, rows):
        b = min(ny, a + rows)
        ii, jj = i0[a:b, None, None], j0[None, :, None]
        py, px = fy[a:b, None, None], fx[None, :, None]
        w00, w01, w10, w11 = (1 - py) * (1 - px), (1 - py) * px, py * (1 - px), py * px
        h = href[a:b, :, None] + (lo[a:b, :, None] + s).double() * step
        t0, ft = _height_segment(h, dh, k0, nh)
        ar = _plane(lat_r, t0, ii, jj, w00, w01, w10, w11)
        br = _plane(lat_r, t0 + 1, ii, jj, w00, w01, w10, w11)
        ac = _plane(lat_c, t0, ii, jj, w00, w01, w10, w11)
        bc = _plane(lat_c, t0 + 1, ii, jj, w00, w01, w10, w11)
        y = ar + ft * (br - ar) - win_r
        x = ac + ft * (bc - ac) - win_c
        out[a:b] = _interpolate(img, y, x, cubic).float()
    return out


def _zncc(s_a, s_b, s_aa, s_bb, s_ab, inv_n: float, eps: float):
    """:func:`tiledsm.match.sweep._zncc` on float64 tensors: ``1 - ZNCC``,
    float32, NaN for a flat window or non-finite sums."""
    torch = _torch()
    va = s_aa - s_a * s_a * inv_n
    vb = s_bb - s_b * s_b * inv_n
    c = (s_ab - s_a * s_b * inv_n) / torch.sqrt(va * vb)
    c = torch.where(c > 1.0, torch.ones_like(c), torch.where(c < -1.0, -torch.ones_like(c), c))
    good = (va > eps * (1.0 + s_aa)) & (vb > eps * (1.0 + s_bb)) & (c == c)
    return torch.where(good, (1.0 - c).float(), torch.full_like(c, float("nan"), dtype=torch.float32))


def _costs(samp, lo, base, half, rows, pairs, pair_w, nd, eps):
    """Costs ``(len(rows), nx - 2 half, nd)`` of the cells of block rows
    ``rows`` (a range inside ``[half, ny - half)``) and columns ``half ..
    nx - half - 1``: the window sums gathered from the neighbours' samples
    at each candidate's absolute label."""
    torch = _torch()
    nv = len(samp)
    ny, nx, ns = samp[0].shape
    wsz = 2 * half + 1
    a, b = rows.start, rows.stop
    k = torch.arange(nd, device=samp[0].device)
    label = base[a:b, half : nx - half, None] + k  # absolute label of every candidate
    nq = 2 * nv + len(pairs)
    win = [None] * nq
    for dc in range(-half, half + 1):
        col = [None] * nq
        for dr in range(-half, half + 1):
            cells = (slice(a + dr, b + dr), slice(half + dc, nx - half + dc))
            idx = (label - lo[cells][..., None]).clamp(0, ns - 1)
            x = [torch.gather(sv[cells], 2, idx).double() for sv in samp]
            terms = x + [xv * xv for xv in x] + [x[u] * x[v] for u, v in pairs]
            col = [t if c is None else c + t for c, t in zip(col, terms)]
        win = [c if w is None else w + c for w, c in zip(win, col)]
    inv_n = 1.0 / (wsz * wsz)
    if len(pairs) == 1:
        return _zncc(win[0], win[1], win[2], win[3], win[4], inv_n, eps)
    tot = torch.zeros(win[0].shape, dtype=torch.float32, device=win[0].device)
    cnt = torch.zeros_like(tot)
    for p, (u, v) in enumerate(pairs):
        cst = _zncc(win[u], win[v], win[nv + u], win[nv + v], win[2 * nv + p], inv_n, eps)
        wp = torch.tensor(pair_w[p], dtype=torch.float32, device=tot.device)
        ok = cst == cst
        tot = torch.where(ok, tot + wp * cst, tot)
        cnt = torch.where(ok, cnt + wp, cnt)
    return torch.where(cnt != 0, tot / cnt, torch.full_like(tot, float("nan")))


def cost_volume(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None, eps: float = 1e-6, device: str = "cpu",
) -> np.ndarray:
    """The SGVLL cost volume of a block on a torch ``device``: the
    arguments and result of :func:`tiledsm.match.sweep.cost_volume`
    (``(ny, nx, nd)`` float32 ``1 - ZNCC``, NaN invalid,
    :data:`~tiledsm.match.sweep.MASKED_COST` beyond a cell's candidates),
    returned as a numpy array."""
    torch = _torch()
    dev = torch.device(device)
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(nvalid.max()))
    base = np.ascontiguousarray(base, np.int64)
    nvalid = np.ascontiguousarray(nvalid, np.int64)
    lo, hi, ns = sample_plan(base, nvalid, half, details)
    vol = empty_volume(nvalid, nd)
    k = np.arange(nd)
    if ns <= 0 or ny <= 2 * half or nx <= 2 * half:
        return vol
    with torch.no_grad():
        lo_t = torch.from_numpy(np.where(lo <= hi, lo, 0)).to(dev)
        href_t = torch.from_numpy(np.ascontiguousarray(href, np.float64)).to(dev)
        samp = [
            _samples(torch.from_numpy(np.ascontiguousarray(imgs[v], np.float32)).to(dev),
                     torch.from_numpy(np.ascontiguousarray(lat_r[v], np.float64)).to(dev),
                     torch.from_numpy(np.ascontiguousarray(lat_c[v], np.float64)).to(dev),
                     int(stride), int(k0), float(dh), href_t, float(step), int(origin[0]), int(origin[1]),
                     int(nodes0[0]), int(nodes0[1]), float(win_r[v]), float(win_c[v]), bool(cubic), lo_t, ns)
            for v in range(nv)
        ]
        pairs, pw = view_pairs(nv, pair_w)
        base_t = torch.from_numpy(base).to(dev)
        step_rows = max(1, _pairs_per_step(dev) // max(1, nx * nd))
        inner = vol[half : ny - half, half : nx - half]
        for a in range(half, ny - half, step_rows):
            rows = range(a, min(ny - half, a + step_rows))
            c = _costs(samp, lo_t, base_t, half, rows, pairs, pw, nd, float(eps)).cpu().numpy()
            part = inner[a - half : rows.stop - half]
            # only the candidates a cell has (the others keep MASKED_COST)
            np.copyto(part, c, where=k < nvalid[a : rows.stop, half : nx - half, None])
    return vol


def _restarts(g, sgn: int, period: int):
    """:func:`tiledsm.match.paths.restarts` of an integer (or integer tensor)
    global index ``g``."""
    if period <= 0:
        return g != g  # never (a tensor of False for a tensor)
    return g % period == 0 if sgn > 0 else (g + 1) % period == 0


def _lines(base, nvalid, gi0: int, gj0: int, period: int, steps: int):
    """Per step (``(steps, m)`` tensors) what each of the ``m = 2 ny + 6
    nx`` paths of the 8 directions does: the cell it reaches (flat index;
    an inactive path, past its line's end, stays on its last cell), its candidates,
    its label shift from its predecessor, whether it restarts there, the
    state row it continues (its predecessor's path) and the row of the
    stacked output it writes (the last row, discarded, when inactive).

    Paths, in state order: along the rows forward then backward (one per
    row; step ``t`` reaches column ``t`` or ``nx - 1 - t``), then the three
    crossing paths (from columns ``j + 1, j, j - 1`` of the previous row: ``nx`` each)
    forward then backward (step ``t`` reaches row ``t`` or ``ny - 1 - t``).
    The outputs are stacked as :func:`aggregate` sums them: forward along
    the row, the three crossing forward, then the same backward."""
    torch = _torch()
    dev = base.device
    ny, nx = base.shape
    t = torch.arange(steps, device=dev)[:, None]
    rows, cols = torch.arange(ny, device=dev)[None, :], torch.arange(nx, device=dev)
    trash = 8 * ny * nx
    parts = []
    # along the rows: restarts at column restart lines and after a gap
    for sgn, vol in ((1, 0), (-1, 4)):
        j = (t if sgn > 0 else nx - 1 - t).clamp(0, nx - 1).expand(steps, ny)
        pj = (j - sgn).clamp(0, nx - 1)
        r = rows.expand(steps, ny)
        restart = (t == 0) | (nvalid[r, pj] == 0) | _restarts(gj0 + j, sgn, period)
        cell = r * nx + j
        out = torch.where(t < nx, vol * ny * nx + cell, torch.full_like(cell, trash))
        prev = rows.expand(steps, ny) + (0 if sgn > 0 else ny)
        parts.append((cell, nvalid[r, j], base[r, j] - base[r, pj], restart, prev, out))
    # across the rows: the three paths from columns j + 1, j, j - 1 of the previous row
    d = torch.arange(3, device=dev).repeat_interleave(nx)
    jj = cols.repeat(3)
    pj = jj + 1 - d
    outside = (pj < 0) | (pj >= nx)
    pj = pj.clamp(0, nx - 1)
    col_restart = torch.cat([_restarts(cols + gj0, -1, period), torch.zeros(nx, dtype=torch.bool, device=dev),
                             _restarts(cols + gj0, 1, period)])
    for sgn, vol, first in ((1, 1, 2 * ny), (-1, 5, 2 * ny + 3 * nx)):
        i = (t if sgn > 0 else ny - 1 - t).clamp(0, ny - 1).expand(steps, 3 * nx)
        pi = (i - sgn).clamp(0, ny - 1)
        jx = jj.expand(steps, 3 * nx)
        restart = ((t == 0) | _restarts(gi0 + i, sgn, period) | outside | (nvalid[pi, pj] == 0)
                   | col_restart)
        cell = i * nx + jx
        out = torch.where(t < ny, (vol + d) * ny * nx + cell, torch.full_like(cell, trash))
        prev = (first + d * nx + pj).expand(steps, 3 * nx)
        parts.append((cell, nvalid[i, jx], base[i, jx] - base[pi, pj], restart, prev, out))
    return [torch.cat([p[k] for p in parts], dim=1) for k in range(6)]


def _paths(cost, base, nvalid, P1, P2: float, gi0: int, gj0: int, period: int):
    """Path costs ``(8 ny nx + 1, nd)`` float32 of the 8 paths
    (:func:`_lines` order; the last row discarded) as
    :func:`tiledsm.match.paths.fast_passes` computes them: at each step, for
    every path, the stay / one-label / P2 transitions from its
    predecessor's costs (gathered at the label shift between the two
    cells' first candidates; a jump beyond the candidates has only P2),
    less the predecessor's minimum, added to the cell's costs in float64;
    +inf beyond a cell's candidates. All paths advance together, one step
    of the longest line at a time, so that a block costs ``max(ny, nx)``
    steps of a few tensor operations each."""
    torch = _torch()
    ny, nx, nd = cost.shape
    dev = cost.device
    steps = max(ny, nx)
    cell, n_here, shift, restart, prev, out = _lines(base, nvalid, gi0, gj0, period, steps)
    m = cell.shape[1]
    pad, width = nd + 1, 3 * nd + 2
    far = (shift > nd) | (shift < -nd)
    # the window of labels k - 1 .. k + 1 of the predecessor, as flat indices into its state row
    start = prev * width + pad - 1 + shift.clamp(-nd, nd)
    window = torch.arange(nd + 2, device=dev)
    k = torch.arange(nd, device=dev)
    flat_cost = cost.reshape(ny * nx, nd)
    paths = torch.empty((8 * ny * nx + 1, nd), dtype=torch.float32, device=dev)
    state = torch.full((m, width), float("inf"), dtype=torch.float32, device=dev)
    after = state.clone()
    mins = torch.zeros(m, dtype=torch.float64, device=dev)
    for s in range(steps):
        c = flat_cost[cell[s]]
        g = state.view(-1)[start[s][:, None] + window]
        side = torch.minimum(g[:, :-2], g[:, 2:]) + P1
        # float32 minus float64: the float64 difference of _update
        trans = torch.minimum(g[:, 1:-1], side) - mins[prev[s]][:, None]
        trans.clamp_(max=float(P2))
        trans.masked_fill_(far[s][:, None], float(P2))
        trans.masked_fill_(restart[s][:, None], 0.0)
        o = c + trans
        o.masked_fill_(k >= n_here[s][:, None], float("inf"))
        mins = o.amin(dim=1)
        mins[2 * ny :] = mins[2 * ny :].float()  # the crossing paths keep float32 minima (cur_min of _pass_fast)
        after[:, pad : pad + nd] = o
        paths.index_copy_(0, out[s], after[:, pad : pad + nd])
        state, after = after, state
    return paths


def aggregate(
    cost: np.ndarray, P1: float, P2: float, base: np.ndarray | None = None, nvalid: np.ndarray | None = None,
    guide: np.ndarray | None = None, p2_gamma: float = 10.0, invalid_cost: float = 1.0,
    origin: tuple[int, int] = (0, 0), restart_period: int = 0, device: str = "cpu",
) -> np.ndarray:
    """Semi-global aggregation over 8 paths on a torch ``device``: the
    arguments and result of :func:`tiledsm.match.sgm.aggregate` (no
    ``guide``), returned as a numpy array."""
    from tiledsm.match.sgm import checked_volume

    if guide is not None:
        raise ValueError("the torch kernel aggregates without a guide image")
    torch = _torch()
    dev = torch.device(device)
    cost, b, n = checked_volume(cost, P1, P2, base, nvalid)
    with torch.no_grad():
        c = torch.from_numpy(np.ascontiguousarray(cost)).to(dev)
        c = torch.where(torch.isfinite(c), c, torch.tensor(np.float32(invalid_cost), device=dev))
        bt = torch.from_numpy(np.ascontiguousarray(b, np.int64)).to(dev)
        nt = torch.from_numpy(np.ascontiguousarray(n, np.int64)).to(dev)
        p1 = torch.tensor(np.float32(P1), device=dev)
        ny, nx, nd = c.shape
        paths = _paths(c, bt, nt, p1, np.float32(P2), int(origin[0]), int(origin[1]), int(restart_period))
        paths = paths[: 8 * ny * nx].view(8, ny, nx, nd)
        # summed in the compiled kernel's order: the forward sweep's four paths, then the backward one's
        S = paths[0]  # in place: the path volumes are not needed after
        for v in range(1, 8):
            S += paths[v]
        return S.cpu().numpy()
