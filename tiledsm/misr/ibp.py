"""Iterative back projection (Irani & Peleg 1991/1993, CVGIP:GMIP 53(3)
231-239), tiled over the HR grid.

Observation model: LR pixel ``p`` of image ``i`` (value ``c_p``) sees the
HR image ``f`` through a PSF ``h`` centred at the pixel's ground position
``(u_p, v_p)`` on the HR grid (continuous cell coordinates, corner
convention: cell ``[i, j]`` spans ``[j, j+1) x [i, i+1)``):

.. math::

    \\hat c_p = \\sum_q w_{pq} f_q / \\sum_q w_{pq}

with ``w`` either the **square** footprint of the LR pixel (``s x s`` HR
cells, ``s`` the scale: area of overlap with each cell) or a **Gaussian**
of ``sigma`` HR cells over the pixel's 8-neighbourhood (``|dx|, |dy| <=
1.5 s``). One iteration:

.. math::

    f^{t+1}_q = f^t_q + \\frac{1}{K_q} \\sum_i
        \\frac{\\sum_{p \\in i} w_{pq} (c_p - \\hat c_p)}{\\sum_{p \\in i} w_{pq}}

(the back-projection kernel is the PSF itself, ``K_q`` the number of images
whose pixels reach ``q``), and ``E(t)`` is the mean of ``(c_p - \\hat c_p)^2``
over every observation. Iterations stop when ``E(t) <= Te`` or after
``max_iter`` updates.

Tiling: an update of the cells of one chunk needs the observations within
``rho`` (the PSF radius) of them, and those need ``f`` within ``rho`` of
themselves, so one iteration is one ``map_blocks`` over ``f`` with a halo of
``2 rho + 2`` cells (``boundary`` NaN: the HR grid's outside is unknown and
left out of the sums). ``E(t)`` is a sum over chunks of the observations
whose centres lie in each chunk: an exact partition. The result does not
depend on the chunking.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import dask.array as da
import numba
import numpy as np

__all__ = ["PSF", "Observations", "ibp"]

_SQUARE, _GAUSS = 0, 1


@dataclass(frozen=True)
class PSF:
    """Point spread function of the observation model.

    Attributes
    ----------
    kind : {"square", "gaussian"}
    sigma : float
        Gaussian standard deviation, HR cells (ignored for the square).
    """

    kind: str = "square"
    sigma: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("square", "gaussian"):
            raise ValueError(f"PSF.kind must be 'square' or 'gaussian', got {self.kind!r}")
        if self.kind == "gaussian" and not self.sigma > 0:
            raise ValueError(f"PSF.sigma must be > 0 HR cells, got {self.sigma!r}")

    @property
    def label(self) -> str:
        return "square" if self.kind == "square" else f"gauss{self.sigma:g}"

    def radius(self, scale: int) -> int:
        """Support radius around an observation's centre, HR cells."""
        return int(math.ceil(scale / 2)) + 1 if self.kind == "square" else int(math.ceil(1.5 * scale)) + 1


@dataclass(frozen=True, eq=False)
class Observations:
    """LR pixels of several images on the HR grid.

    ``u``, ``v`` (columns, rows; continuous HR cell coordinates), ``c``
    (grey levels, adjusted to the reference) and ``image`` (index of the
    image each comes from, 0..n-1, sorted), 1-D arrays of one length.
    """

    u: np.ndarray
    v: np.ndarray
    c: np.ndarray
    image: np.ndarray

    @property
    def n_images(self) -> int:
        return int(self.image.max()) + 1 if self.image.size else 0


@numba.njit(nogil=True, cache=True, inline="always")
def _weight(kind, d, scale, sigma):
    """1-D PSF weight of a cell whose centre is ``d`` cells from the
    observation's centre (separable)."""
    if kind == 0:
        half = 0.5 * scale
        lo = max(d - 0.5, -half)
        hi = min(d + 0.5, half)
        return max(hi - lo, 0.0)
    if abs(d) > 1.5 * scale:
        return 0.0
    return math.exp(-0.5 * d * d / (sigma * sigma))


@numba.njit(nogil=True, cache=True)
def _close_image(num, den, total, count):
    """Add one image's back projection ``num / den`` to the running sum
    ``total`` (and ``count``) where it reaches, and reset ``num``, ``den``."""
    for i in range(num.shape[0]):
        for j in range(num.shape[1]):
            if den[i, j] > 0:
                total[i, j] += num[i, j] / den[i, j]
                count[i, j] += 1.0
                num[i, j] = 0.0
                den[i, j] = 0.0


@numba.njit(nogil=True, cache=True)
def _ibp_block(f, r0, c0, core_r, core_c, u, v, c, image, n_images, kind, scale, sigma, rho, out, err):
    """One IBP update of the core of block ``f`` (``f[i, j]`` is HR cell
    ``(r0 + i, c0 + j)``, core = rows ``core_r[0]:core_r[1]``, columns
    ``core_c[0]:core_c[1]`` of the block); ``out`` receives the core's new
    values, ``err[0:2]`` the squared error sum and count of the
    observations centred in the core."""
    ny, nx = f.shape
    cr0, cr1 = core_r
    cc0, cc1 = core_c
    hy, hx = cr1 - cr0, cc1 - cc0
    total = np.zeros((hy, hx))
    count = np.zeros((hy, hx))
    num = np.zeros((hy, hx))
    den = np.zeros((hy, hx))
    wy = np.empty(2 * rho + 2)
    wx = np.empty(2 * rho + 2)
    current = -1
    for p in range(u.size):
        if image[p] != current:
            # close the previous image's back projection
            if current >= 0:
                _close_image(num, den, total, count)
            current = image[p]
        # block coordinates of the observation's centre
        y = v[p] - r0
        x = u[p] - c0
        if y < cr0 - rho - 1 or y > cr1 + rho + 1 or x < cc0 - rho - 1 or x > cc1 + rho + 1:
            continue
        i0 = int(math.floor(y)) - rho
        j0 = int(math.floor(x)) - rho
        n = 2 * rho + 2
        for m in range(n):
            wy[m] = _weight(kind, (i0 + m + 0.5) - y, scale, sigma)
            wx[m] = _weight(kind, (j0 + m + 0.5) - x, scale, sigma)
        s = 0.0
        sw = 0.0
        for m in range(n):
            ii = i0 + m
            if wy[m] == 0.0 or ii < 0 or ii >= ny:
                continue
            for q in range(n):
                jj = j0 + q
                if wx[q] == 0.0 or jj < 0 or jj >= nx:
                    continue
                val = f[ii, jj]
                if val == val:
                    w = wy[m] * wx[q]
                    s += w * val
                    sw += w
        if sw <= 0.0:
            continue
        e = c[p] - s / sw
        if y >= cr0 and y < cr1 and x >= cc0 and x < cc1:
            err[0] += e * e
            err[1] += 1.0
        for m in range(n):
            ii = i0 + m - cr0
            if wy[m] == 0.0 or ii < 0 or ii >= hy:
                continue
            for q in range(n):
                jj = j0 + q - cc0
                if wx[q] == 0.0 or jj < 0 or jj >= hx:
                    continue
                w = wy[m] * wx[q]
                num[ii, jj] += w * e
                den[ii, jj] += w
    if current >= 0:
        _close_image(num, den, total, count)
    for i in range(hy):
        for j in range(hx):
            base = f[cr0 + i, cc0 + j]
            if count[i, j] > 0 and base == base:
                out[i, j] = base + total[i, j] / count[i, j]
            else:
                out[i, j] = base


def _task(block, *, obs: Observations, layout, depth: int, psf: PSF, scale: int, what: str, block_id=None):
    bi, bj = block_id[:2]
    R0, C0 = sum(layout[0][:bi]), sum(layout[1][:bj])
    h, w = layout[0][bi], layout[1][bj]
    f = np.ascontiguousarray(block, np.float64)
    out = np.empty((h, w))
    err = np.zeros(2)
    kind = _SQUARE if psf.kind == "square" else _GAUSS
    _ibp_block(f, R0 - depth, C0 - depth, (depth, depth + h), (depth, depth + w), obs.u, obs.v, obs.c, obs.image,
               obs.n_images, kind, float(scale), float(psf.sigma), psf.radius(scale), out, err)
    if what == "error":
        return err.reshape(1, 1, 2)
    return out


def ibp(
    init: np.ndarray,
    obs: Observations,
    psf: PSF,
    scale: int,
    *,
    chunk: int = 512,
    max_iter: int = 20,
    te: float = 0.0,
) -> tuple[np.ndarray, dict]:
    """Run IBP from ``init`` (module docstring).

    Parameters
    ----------
    init : (H, W) array
        Initial HR image (e.g. the SR-R average), NaN = unknown.
    obs : Observations
    psf : PSF
    scale : int
        LR/HR cell ratio.
    chunk : int
        Chunk side of the HR grid, cells.
    max_iter : int
        Maximum number of updates.
    te : float
        Stop when the mean squared error ``E(t)`` (DN^2) is <= ``te``.

    Returns
    -------
    f : numpy.ndarray
        float32 HR image.
    report : dict
        ``iterations`` (updates applied), ``errors`` (``E(t)`` per
        iteration, the first for ``init``), ``halo`` (cells).
    """
    depth = 2 * psf.radius(scale) + 2
    f = np.asarray(init, np.float64)
    errors: list[float] = []
    iterations = 0
    for t in range(max_iter + 1):
        arr = da.from_array(f, chunks=(chunk, chunk))
        if depth > min(min(c) for c in arr.chunks):
            from tiledsm.dsm import level_chunks

            arr = arr.rechunk(tuple(level_chunks(n, max(chunk, depth), min(depth, n)) for n in f.shape))
        dep = tuple(min(depth, n) for n in f.shape)
        padded = da.overlap.overlap(arr, depth={0: dep[0], 1: dep[1]}, boundary=np.nan)
        common = dict(obs=obs, layout=arr.chunks, depth=dep[0], psf=psf, scale=scale, dtype=np.float64)
        if dep[0] != dep[1]:
            raise ValueError("ibp: HR grid smaller than the halo along one axis only")
        errs = padded.map_blocks(_task, what="error", chunks=((1,) * arr.numblocks[0], (1,) * arr.numblocks[1], (2,)),
                                 new_axis=2, **common)
        upd = padded.map_blocks(_task, what="update", chunks=arr.chunks, **common)
        if t < max_iter:
            e, new = da.compute(errs, upd)
        else:
            (e,), new = da.compute(errs), None
        e = e.reshape(-1, 2).sum(0)
        E = float(e[0] / e[1]) if e[1] else float("nan")
        errors.append(E)
        if new is None or E <= te:
            break
        f = new
        iterations += 1
    return f.astype(np.float32), {"iterations": iterations, "errors": errors, "halo": depth}
