"""The displacement field of two orthoimages: one ``map_overlap`` over the
ortho grid (:func:`correlate_orthos`), or, for orthos stored as zarr
stores, one ``map_blocks`` whose tasks read their own window and halo from
the stores.

Why the second form: with ``map_overlap`` every block waits for pieces of
its neighbours, so the scheduler holds a frontier of input chunks (and
their halo slices) about a chunk row wide; measured on a 16384² pair with
1024 px chunks, 1271 MiB per worker against 408 MiB at 2048². Read from
the stores, a task needs nothing but its window: memory per worker does
not grow with the scene (``benchmarks/displacement_memory.py``).

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
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.displace.correlate import N_LAYERS, CorrelationParams
from tiledsm.displace.pyramid import correlate_cells
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


def _deep_chunks(n: int, side: int, depth: int) -> tuple[int, ...]:
    """Chunks of ``side`` along ``n`` pixels, the last merged into the one
    before when it is shallower than ``depth`` (dask's overlap needs every
    chunk at least as deep as the halo); ``side`` a multiple of the step."""
    sizes = [side] * (n // side) + ([n % side] if n % side else [])
    if len(sizes) > 1 and sizes[-1] < depth:
        sizes[-2:] = [sizes[-2] + sizes[-1]]
    return tuple(sizes)


def _field_block(pre, post, *, params: CorrelationParams, halo: int, block_info=None) -> np.ndarray:
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    return correlate_cells(pre, post, r1 - r0, c1 - c0, params, halo, (r0, c0))


def _read_window(store: str, name: str, r0: int, r1: int, c0: int, c1: int, shape: tuple[int, int]) -> np.ndarray:
    """Pixels ``[r0, r1) x [c0, c1)`` of a stored ortho as float32, NaN
    outside ``[0, shape[0]) x [0, shape[1])`` (decoded as xarray does:
    fill values become NaN)."""
    out = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
    a0, a1, b0, b1 = max(r0, 0), min(r1, shape[0]), max(c0, 0), min(c1, shape[1])
    if a1 > a0 and b1 > b0:
        # chunks=None: a lazily indexed backend array, only the window is read (no dask inside the task)
        with xr.open_zarr(store, chunks=None, decode_coords=False, consolidated=False, zarr_format=3) as ds:
            out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = ds[name][a0:a1, b0:b1].values
    return out


def _store_block(*, pre: tuple[str, str], post: tuple[str, str], shape: tuple[int, int], params: CorrelationParams,
                 halo: int, block_info=None) -> np.ndarray:
    (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
    s = params.step
    win = (r0 * s - halo, r1 * s + halo, c0 * s - halo, c1 * s + halo)
    a = _read_window(*pre, *win, shape)
    b = _read_window(*post, *win, shape)
    return correlate_cells(a, b, r1 - r0, c1 - c0, params, halo, (r0, c0))


def correlate_orthos(pre: xr.DataArray | str | Path, post: xr.DataArray | str | Path,
                     params: CorrelationParams = CorrelationParams(), *, chunk: int = 1024) -> xr.Dataset:
    """Lazy displacement field of ``post`` against ``pre``.

    Parameters
    ----------
    pre, post : xarray.DataArray or path-like
        Orthoimages ``(y, x)`` on one north-up grid (rioxarray CRS and
        transform), NaN = no data; or the zarr stores of two such orthos
        (as written by :func:`tiledsm.io.write_zarr`), whose windows every
        task then reads itself (module notes: memory that does not grow
        with the scene). Both forms give identical values.
    params : CorrelationParams
    chunk : int
        Ortho pixels per chunk side (rounded to a multiple of ``params.step``).

    Returns
    -------
    xarray.Dataset
        ``dE``, ``dN`` (metres), ``quality``, ``texture``, ``peak``,
        ``formal_dE``, ``formal_dN`` (metres) on the ortho grid
        coarsened ``params.step`` times (module notes), dask-backed, CRS and
        transform written; attrs hold the parameters.

    Raises
    ------
    GridError
        The orthos are not on one grid, or the grid is smaller than one window.
    """
    import rioxarray  # noqa: F401

    from tiledsm.io import open_product

    stores = None
    if isinstance(pre, (str, Path)) or isinstance(post, (str, Path)):
        if not (isinstance(pre, (str, Path)) and isinstance(post, (str, Path))):
            raise TypeError("correlate_orthos: give two DataArrays or two store paths")
        paths = (Path(pre), Path(post))
        pre, post = (open_product(p) for p in paths)
        for p, a in zip(paths, (pre, post)):
            if not isinstance(a, xr.DataArray) or a.ndim != 2:
                raise GridError(f"{p}: not a single-band ortho store (write it from one 2-D DataArray)")
        stores = tuple((str(p), str(a.name)) for p, a in zip(paths, (pre, post)))  # the stored variable
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
    if stores is not None:
        # every task reads its block and `depth` pixels around it (NaN past the cropped grid) itself
        from dask.base import tokenize

        cells = tuple(tuple(n // s for n in cs) for cs in da.core.normalize_chunks(c, (ny * s, nx * s)))
        raw = da.map_blocks(
            _store_block, chunks=((N_LAYERS,), *cells), dtype=np.float32, meta=np.empty((0, 0, 0), np.float32),
            pre=stores[0], post=stores[1], shape=(ny * s, nx * s), params=params, halo=depth,
            name=f"correlate-{tokenize(stores, params, c)}",
        )
    else:
        arrays = []
        for a in (pre, post):
            d = a.data if isinstance(a.data, da.Array) else da.from_array(np.asarray(a.values))
            arrays.append(d[: ny * s, : nx * s].astype(np.float32).rechunk(c))
        # dask's overlap needs chunks at least as deep as the halo
        if min(min(cs) for cs in arrays[0].chunks) < depth:
            side = max(c, depth + s - depth % s)
            arrays = [a.rechunk(tuple(_deep_chunks(n, side, depth) for n in a.shape)) for a in arrays]
        chunks_out = ((N_LAYERS,), tuple(n // s for n in arrays[0].chunks[0]), tuple(n // s for n in arrays[0].chunks[1]))
        # one map_overlap: every block sees `depth` pixels of its neighbours
        # (NaN past the grid) and returns its (6, cells, cells)
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
            "formal_dE": (("y", "x"), raw[5] * np.float32(abs(res_x))),
            "formal_dN": (("y", "x"), raw[4] * np.float32(abs(res_y))),
            "peak": (("y", "x"), raw[6]),
        },
        coords={"y": y, "x": x},
    )
    from affine import Affine

    ds = ds.rio.write_crs(pre.rio.crs).rio.write_transform(Affine(res_x * s, 0, t.c, 0, res_y * s, t.f))
    ds["dE"].attrs.update(units="m", long_name="east displacement (post - pre)")
    ds["dN"].attrs.update(units="m", long_name="north displacement (post - pre)")
    ds["quality"].attrs.update(units="1", long_name="phase coherence of the correlation")
    ds["texture"].attrs.update(long_name="standard deviation of the pre window")
    ds["peak"].attrs.update(units="1", long_name="height of the phase-correlation peak")
    for n in ("dE", "dN"):
        ds[f"formal_{n}"].attrs.update(units="m", long_name=f"formal standard error of {n} (phase-plane fit)")
    ds.attrs.update({f"correlation_{k}": v for k, v in vars(params).items()})
    return ds

