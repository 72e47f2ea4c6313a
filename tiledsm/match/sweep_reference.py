"""The reference sweep of the SGVLL cost volume (kernel ``"reference"``):
one candidate height at a time over the bounding box of the cells that need
it, the plain form :func:`tiledsm.match.sweep.cost_volume` (kernel
``"fast"``) is tested against."""

from __future__ import annotations

import numba as nb
import numpy as np

from tiledsm.match.cost import mean_zncc_cost
from tiledsm.match.sampling import sample_view
from tiledsm.match.sweep import MASKED_COST

__all__ = ["cost_volume_reference"]


@nb.njit(nogil=True, cache=True)
def _scatter(cost, label, base, nvalid, r0, c0, vol):
    """``vol[i, j, label - base[i, j]] = cost[i - r0, j - c0]`` where that
    candidate exists."""
    h, w = cost.shape
    for a in range(h):
        i = a + r0
        for b in range(w):
            j = b + c0
            k = label - base[i, j]
            if 0 <= k < nvalid[i, j]:
                vol[i, j, k] = cost[a, b]


def cost_volume_reference(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None,
) -> np.ndarray:
    """The SGVLL cost volume of a block, one candidate height at a time
    (the plain reference of :func:`tiledsm.match.sweep.cost_volume`, same
    arguments and result): for every label some cell needs, every view is
    resampled over the bounding box of those cells (plus the window) on
    the surface ``href + label * step``
    (:func:`~tiledsm.match.sampling.sample_view`), scored by
    :func:`~tiledsm.match.cost.mean_zncc_cost` and scattered into the
    cells' candidates."""
    # float32 windows, as the fast kernel's (bicubic samples are float32 sums)
    imgs = [np.ascontiguousarray(im, np.float32) for im in imgs]
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(nvalid.max()))
    ok = nvalid > 0
    gi0, gj0 = (int(o) for o in origin)
    n0i, n0j = (int(n) for n in nodes0)
    vol = np.full((ny, nx, nd), MASKED_COST, np.float32)
    buf = np.empty((nv, ny, nx), np.float32)
    top_lab = base + nvalid - 1
    n_samples = 0
    for label in range(int(base[ok].min()), int(top_lab[ok].max()) + 1):
        need = ok & (base <= label) & (top_lab >= label)
        rows = np.flatnonzero(need.any(axis=1))
        if rows.size == 0:
            continue
        cols = np.flatnonzero(need.any(axis=0))
        r0, r1 = max(0, rows[0] - half), min(ny, rows[-1] + half + 1)
        c0, c1 = max(0, cols[0] - half), min(nx, cols[-1] + half + 1)
        samples = []
        for v in range(nv):
            sample_view(
                imgs[v], lat_r[v], lat_c[v], stride, k0, dh, href, label * step, gi0, gj0, n0i, n0j,
                win_r[v], win_c[v], cubic, r0, r1, c0, c1, buf[v],
            )
            samples.append(buf[v, : r1 - r0, : c1 - c0])
        cost = mean_zncc_cost(samples, half, weights=pair_w)
        _scatter(cost, label, base, nvalid, r0, c0, vol)
        n_samples += (r1 - r0) * (c1 - c0)
    if details is not None:
        details["n_samples"] = n_samples
    return vol
