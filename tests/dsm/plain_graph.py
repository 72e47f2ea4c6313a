"""The test oracle of the DSM engine: the plain dask graph that matched
every level before the engine wrote levels to stores (until issue 35 the
package's in-memory engine). A finer level's tasks take the coarser
level's heights through an overlap (:func:`coarse_blocks`), the speckle
filter its level's matched chunks through another (:func:`despeckle`): no
store, no tokens, another route to the same heights. The matching of one
chunk (:func:`tiledsm.dsm.levels.match_task`) and the layout are the
package's.
"""

from __future__ import annotations

import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.dsm.layout import LevelLayout, level_layout
from tiledsm.dsm.levels import auto_levels, level_geometry, match_task


def _overlap(x: da.Array, depth: dict[int, int]) -> da.Array:
    depth = {ax: (d if len(x.chunks[ax]) > 1 else 0) for ax, d in depth.items()}
    return da.overlap.overlap(x, depth=depth, boundary="none", allow_rechunk=False)


def coarse_blocks(coarse: da.Array, layout: LevelLayout) -> da.Array:
    """The coarser level's heights as one block per finer chunk: rechunked
    to half the finer chunks, each block grown by the coarse depth (NaN
    beyond the grid)."""
    depth = layout.coarse_depth
    halves = tuple(
        tuple(n // 2 for n in ch[:-1]) + (nc - sum(n // 2 for n in ch[:-1]),) for ch, nc in zip(layout.chunks, coarse.shape)
    )
    c = coarse.rechunk(halves)
    padded = da.pad(c, depth, mode="constant", constant_values=np.nan)
    padded = padded.rechunk(
        tuple((ch[0] + depth,) + ch[1:-1] + (ch[-1] + depth,) if len(ch) > 1 else (ch[0] + 2 * depth,) for ch in c.chunks)
    )
    return _overlap(padded, {0: depth, 1: depth})


def _despeckle_heights(block: np.ndarray, max_diff: float, min_size: int) -> np.ndarray:
    from tiledsm.match.sgm import remove_speckles

    out = block.copy()
    out[0] = remove_speckles(block[0], max_diff, min_size)
    return out


def despeckle(matched: da.Array, layout: LevelLayout) -> da.Array:
    """The whole level's speckle filter as one ``map_overlap`` with a halo
    of the filter's size."""
    size = layout.speckle_size
    if size <= 1:
        return matched
    chunks = matched.chunks
    short = {ax: -1 for ax in (1, 2) if matched.shape[ax] <= size}
    depth = {0: 0, **{ax: (0 if ax in short else size) for ax in (1, 2)}}
    out = da.map_overlap(
        _despeckle_heights, matched.rechunk(short) if short else matched, depth=depth, boundary="none", trim=True,
        dtype=np.float32, max_diff=layout.speckle_max_diff, min_size=size,
    )
    return out.rechunk(chunks)


def _match(coarse, views, geom, layout, h_range, params, block_id=None):
    return match_task(coarse, views, geom, layout, h_range, params, *block_id[-2:])


def _match_coarsest(_, views, geom, layout, h_range, params, block_id=None):
    return match_task(None, views, geom, layout, h_range, params, *block_id[-2:])


def level_array(views, geom, layout: LevelLayout, h_range, params, coarse: da.Array | None) -> da.Array:
    """Lazy ``(2, H, W)`` heights and confidence of one level in the
    layout's chunks, speckles removed."""
    if coarse is None:
        blocks = da.zeros((1, *layout.shape), chunks=((1,), *layout.chunks), dtype=np.uint8)
        fn = _match_coarsest
    else:
        blocks, fn = coarse_blocks(coarse, layout), _match
    matched = da.map_blocks(
        fn, blocks, views, geom, layout, tuple(h_range), params,
        chunks=((2,), *layout.chunks), dtype=np.float32, new_axis=None if coarse is None else 0,
    )
    return despeckle(matched, layout)


def plain_dsm(views, grid, h_range, params) -> xr.Dataset:
    """``height`` and ``confidence`` of the plain graph, on ``grid``."""
    levels = params.levels or auto_levels(views, grid, h_range, params)
    arr = None
    for level in range(levels - 1, -1, -1):
        geom = level_geometry(views, grid, level, h_range, params, levels)
        arr = level_array(views, geom, level_layout(geom, grid.chunk, params), h_range, params,
                          None if arr is None else arr[0])
    arr = arr.rechunk(((2,), *grid.chunks))
    return xr.Dataset({"height": (("y", "x"), arr[0]), "confidence": (("y", "x"), arr[1])})
