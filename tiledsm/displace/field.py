"""The displacement field of two orthoimages: one ``map_overlap`` over the
ortho grid (:func:`correlate_orthos`).

The output grid is the ortho grid coarsened by ``step``: output cell
``(i, j)`` covers ortho pixels ``[i*step, (i+1)*step) x [j*step,
(j+1)*step)`` and its correlation window is centred on that cell's centre.
Each window only reads pixels within ``params.halo`` of its centre, and the
halo of every block is at least that, so the field does not depend on the
chunking (tested: chunks of 256 and 1024 give identical values).

Units: ``dE``/``dN`` metres east/north (``post`` against ``pre``: the ground
at a cell moved by ``(dE, dN)`` between the two images); ``quality`` the
phase coherence in ``[0, 1]``; ``texture`` the standard deviation of the
``pre`` window (image units).
"""

from __future__ import annotations

import logging

import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.displace.correlate import CorrelationParams, correlate_windows
from tiledsm.errors import GridError

__all__ = ["correlate_orthos", "field_chunk", "check_same_grid"]

log = logging.getLogger("tiledsm.displace")


def check_same_grid(pre: xr.DataArray, post: xr.DataArray, pre_name: str = "pre", post_name: str = "post") -> None:
    """Refuse two orthos that are not on one grid (CRS, transform, shape):
    correlating them would measure the grid offset as ground motion."""
    import rioxarray  # noqa: F401

    problems = []
    if pre.shape != post.shape:
        problems.append(f"shape {pre.shape} vs {post.shape}")
    if pre.rio.crs != post.rio.crs:
        problems.append(f"CRS {pre.rio.crs} vs {post.rio.crs}")
    ta, tb = pre.rio.transform(), post.rio.transform()
    if not np.allclose(tuple(ta)[:6], tuple(tb)[:6], rtol=0, atol=1e-6 * abs(ta.a)):
        problems.append(f"transform {tuple(ta)[:6]} vs {tuple(tb)[:6]}")
    if problems:
        raise GridError(
            f"{pre_name} and {post_name} are not on the same grid ({'; '.join(problems)}): orthorectify both on "
            "one DSM grid (the post-event DSM made on the pre-event DSM's grid, as the deformation pipeline does)"
        )


def field_chunk(chunk: int, step: int) -> int:
    """The ortho chunk actually used: a multiple of ``step`` near ``chunk``."""
    return max(step, int(round(chunk / step)) * step)


def _field_block(pre, post, *, params: CorrelationParams, halo: int, block_info=None) -> np.ndarray:
    """Cells of one output block: ``pre``/``post`` are the block's ortho
    pixels plus ``halo`` pixels on every side (NaN past the grid)."""
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    s = params.step
    # window centres (GDAL coordinates of the block): the middle of each output cell
    rows = halo + (np.arange(r1 - r0) + 0.5) * s
    cols = halo + (np.arange(c1 - c0) + 0.5) * s
    R, C = np.meshgrid(rows.astype(np.int64), cols.astype(np.int64), indexing="ij")
    out = correlate_windows(pre, post, R.ravel(), C.ravel(), params)
    return out.reshape(4, r1 - r0, c1 - c0)


def correlate_orthos(pre: xr.DataArray, post: xr.DataArray, params: CorrelationParams = CorrelationParams(),
                     *, chunk: int = 1024) -> xr.Dataset:
    """Lazy displacement field of ``post`` against ``pre``.

    Parameters
    ----------
    pre, post : xarray.DataArray
        Orthoimages ``(y, x)`` on one north-up grid (rioxarray CRS and
        transform), NaN = no data.
    params : CorrelationParams
    chunk : int
        Ortho pixels per chunk side (rounded to a multiple of ``params.step``).

    Returns
    -------
    xarray.Dataset
        ``dE``, ``dN`` (metres), ``quality``, ``texture`` on the ortho grid
        coarsened ``params.step`` times (module notes), dask-backed, CRS and
        transform written; attrs hold the parameters.

    Raises
    ------
    GridError
        The orthos are not on one grid, or the grid is smaller than one window.
    """
    import rioxarray  # noqa: F401

    check_same_grid(pre, post)
    s = params.step
    ny, nx = (n // s for n in pre.shape)
    if ny < 1 or nx < 1 or min(pre.shape) < params.window:
        raise GridError(f"the orthos ({pre.shape[0]} x {pre.shape[1]} px) are smaller than one "
                        f"correlation window ({params.window} px)")
    t = pre.rio.transform()
    res_x, res_y = float(t.a), float(t.e)
    c = field_chunk(chunk, s)
    depth = params.halo
    arrays = []
    for a in (pre, post):
        d = a.data if isinstance(a.data, da.Array) else da.from_array(np.asarray(a.values))
        arrays.append(d[: ny * s, : nx * s].astype(np.float32).rechunk(c))
    chunks_out = ((4,), tuple(n // s for n in arrays[0].chunks[0]), tuple(n // s for n in arrays[0].chunks[1]))
    # dask's overlap needs chunks at least as deep as the halo
    if min(min(cs) for cs in arrays[0].chunks) < depth:
        arrays = [a.rechunk(max(c, depth + s - depth % s)) for a in arrays]
        chunks_out = ((4,), tuple(n // s for n in arrays[0].chunks[0]), tuple(n // s for n in arrays[0].chunks[1]))
    # one map_overlap: every block sees `depth` pixels of its neighbours
    # (NaN past the grid) and returns its (4, cells, cells)
    raw = da.map_overlap(
        _field_block, *arrays, depth=depth, boundary=np.nan, trim=False, align_arrays=False,
        new_axis=0, chunks=chunks_out, dtype=np.float32, meta=np.empty((0, 0, 0), np.float32),
        params=params, halo=depth,
    )
    x = float(t.c) + (np.arange(nx) + 0.5) * s * res_x
    y = float(t.f) + (np.arange(ny) + 0.5) * s * res_y
    # rows grow southward (res_y < 0): a shift of +dy rows is a move of dy * res_y metres north
    ds = xr.Dataset(
        {
            "dE": (("y", "x"), raw[1] * np.float32(res_x)),
            "dN": (("y", "x"), raw[0] * np.float32(res_y)),
            "quality": (("y", "x"), raw[2]),
            "texture": (("y", "x"), raw[3]),
        },
        coords={"y": y, "x": x},
    )
    from affine import Affine

    ds = ds.rio.write_crs(pre.rio.crs).rio.write_transform(Affine(res_x * s, 0, t.c, 0, res_y * s, t.f))
    ds["dE"].attrs.update(units="m", long_name="east displacement (post - pre)")
    ds["dN"].attrs.update(units="m", long_name="north displacement (post - pre)")
    ds["quality"].attrs.update(units="1", long_name="phase coherence of the correlation")
    ds["texture"].attrs.update(long_name="standard deviation of the pre window")
    ds.attrs.update({f"correlation_{k}": v for k, v in vars(params).items()})
    return ds

