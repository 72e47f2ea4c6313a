"""Vertical displacement read at the displaced position (one ``map_overlap``).

``dU`` of a field cell is the median, over the DSM cells ``p`` of that
field cell, of ``post(p + d) - pre(p)``, where ``d = (dE, dN)`` is the
cell's horizontal displacement and ``post`` the co-registered post-event
DSM (bilinear). Reading ``post`` where the ground went, not at ``p``,
keeps a slope that moved sideways from reading as uplift: on a slope of
gradient ``g``, ``post(p) - pre(p)`` is off by ``g . d``.

Grids: ``pre`` and ``post`` on one DSM grid (metres, north-up), the field
on that grid coarsened ``step`` times (:mod:`tiledsm.displace.field`).
Returned with ``dU`` is the median slope of ``pre`` in each field cell
(degrees), the predictor of ``dU``'s uncertainty.
"""

from __future__ import annotations

import math

import dask.array as da
import numpy as np

from tiledsm.ortho.kernels import sample

__all__ = ["vertical_displacement", "vertical_block"]


def vertical_block(pre: np.ndarray, post: np.ndarray, dE: np.ndarray, dN: np.ndarray, *, step: int, res: float,
                   halo: int) -> np.ndarray:
    """``(dU, slope_deg)`` of the field cells of one block (pure).

    ``pre``/``post`` are the block's DSM cells plus ``halo`` cells on every
    side (NaN past the grid); ``dE``/``dN`` the block's field cells (metres).
    """
    ny, nx = dE.shape
    core = pre[halo:halo + ny * step, halo:halo + nx * step]
    # slope of pre by central differences on the block (halo gives the neighbours)
    gy, gx = np.gradient(pre.astype(np.float64), res)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))[halo:halo + ny * step, halo:halo + nx * step]
    # DSM cell centres of the core in GDAL coordinates of the block, moved by each field cell's d
    fy = np.repeat(np.repeat(-np.asarray(dN, np.float64) / res, step, 0), step, 1)
    fx = np.repeat(np.repeat(np.asarray(dE, np.float64) / res, step, 0), step, 1)
    r = halo + np.arange(ny * step)[:, None] + 0.5 + fy
    c = halo + np.arange(nx * step)[None, :] + 0.5 + fx
    moved = sample(post, r, c, "bl")
    du = (moved - core).reshape(ny, step, nx, step)
    sl = slope.reshape(ny, step, nx, step)
    out = np.full((2, ny, nx), np.nan, np.float32)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN cells stay NaN
            out[0] = np.nanmedian(du, axis=(1, 3))
            out[1] = np.nanmedian(sl, axis=(1, 3))
    # a field cell needs most of its DSM cells (else its median is a few cells' noise)
    share = np.isfinite(du).mean(axis=(1, 3))
    out[0][share < 0.5] = np.nan
    return out


def _block(pre, post, dE, dN, *, step, res, halo):
    return vertical_block(pre, post, dE, dN, step=step, res=res, halo=halo)


def vertical_displacement(pre: da.Array, post: da.Array, dE: da.Array, dN: da.Array, *, step: int,
                          res: float) -> da.Array:
    """Lazy ``(2, ny, nx)``: ``dU`` (metres) and the median slope of ``pre``
    (degrees) on the field grid (module notes).

    ``pre``/``post`` ``(ny*step, nx*step)`` or larger (cropped), ``dE``/``dN``
    ``(ny, nx)`` metres; the field's NaN give NaN.
    """
    ny, nx = dE.shape
    dmax = float(da.nanmax(da.hypot(dE, dN)).compute()) if dE.size else 0.0
    halo = int(math.ceil((0 if not np.isfinite(dmax) else dmax) / res)) + 3
    c = dE.chunks
    fine = tuple(tuple(n * step for n in cs) for cs in c)
    pre = pre[: ny * step, : nx * step].astype(np.float32).rechunk(fine)
    post = post[: ny * step, : nx * step].astype(np.float32).rechunk(fine)
    if min(min(cs) for cs in fine) < halo:
        raise ValueError(f"vertical_displacement: chunks of {min(min(cs) for cs in fine)} DSM cells are thinner than "
                         f"the {halo}-cell halo the displacement needs; use larger chunks")
    return da.map_overlap(
        _block, pre, post, dE.astype(np.float64), dN.astype(np.float64), depth=[halo, halo, 0, 0],
        boundary=[np.nan, np.nan, "none", "none"], trim=False, align_arrays=False, new_axis=0,
        chunks=((2,), *c), dtype=np.float32, meta=np.empty((0, 0, 0), np.float32), step=step, res=res, halo=halo,
    )
