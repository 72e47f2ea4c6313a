"""One pyramid level of the DSM: its grid, geometry, chunk layout and the
dask graph that matches it chunk by chunk (each task a chunk plus its halo),
searching around the coarser level, then removing speckles."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import dask.array as da
import numpy as np

from tiledsm.errors import MatchingError
from tiledsm.geometry.grid import GroundGrid
from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.views import View, read_window


# --------------------------------------------------------------------- blocks
def level_grid(grid: GroundGrid, level: int) -> GroundGrid:
    """The grid of pyramid level ``level``: cells ``2**level`` times larger,
    same top-left corner (coarse cell ``I`` covers cells ``2I, 2I+1`` of the
    next finer level), same chunk side in cells."""
    from tiledsm.match.pyramid import level_shape

    f = 2**level
    h, w = level_shape(grid.shape, level)
    return GroundGrid(crs=grid.crs, x0=grid.x0, y0=grid.y0, resolution=grid.resolution * f, width=w, height=h, chunk=grid.chunk)


@dataclass(frozen=True)
class LevelGeometry:
    """What every task of one pyramid level shares: its grid, image
    decimation, height step and view-pair weights, all measured once at the
    grid centre so that every chunk sweeps the same candidate lattice and
    scores candidates the same way.

    Attributes
    ----------
    level : int
        0 = full resolution.
    grid : GroundGrid
        The level's grid (:func:`level_grid`).
    step : float
        Height step, metres (about ``step_px`` pixels of parallax).
    pair_weights : numpy.ndarray
        ``(nv, nv)`` squared parallax per metre of each view pair.
    """

    level: int
    grid: GroundGrid
    step: float
    pair_weights: np.ndarray

    @property
    def factor(self) -> int:
        return 2**self.level


def level_geometry(
    views: Sequence[View], grid: GroundGrid, level: int, h_range, params: DSMParams, levels: int = 1
) -> LevelGeometry:
    """The :class:`LevelGeometry` of level ``level`` of a pyramid of
    ``levels`` levels over ``grid``.

    With two or more levels, the coarsest (``levels - 1``) sweeps the whole
    height range with steps ``params.sweep_step_factor`` times its own
    (see :class:`~tiledsm.dsm.params.DSMParams`)."""
    from tiledsm.match.sgvll import height_step, pair_weights

    lgrid = level_grid(grid, level)
    lon, lat = _grid_centre_lonlat(lgrid)
    f = 2**level
    rpcs = [v.rpc.scaled(1.0 / f) if f > 1 else v.rpc for v in views]
    h = float(np.mean(h_range))
    step = float(height_step(rpcs, lon, lat, h, params.match))
    if level > 0 and level == levels - 1:
        step *= params.sweep_step_factor
    return LevelGeometry(level, lgrid, step, pair_weights(rpcs, lon, lat, h))


def _level_image(view: View, sub: GroundGrid, h_band: tuple[float, float], f: int):
    """Pixels of ``view`` that see the ground cells ``sub`` over ``h_band``,
    at decimation ``f``: ``(image, (row0, col0))`` with the window's origin
    in pixels of the decimated image, or ``None`` when the view does not
    see the cells (or sees only nodata).

    The window's origin is a multiple of ``f`` in the full image, so its
    decimated pixels are exactly those of the whole decimated image
    (whichever chunk asks for them).
    """
    from tiledsm.geometry.footprint import image_window
    from tiledsm.match.pyramid import downsample

    win = image_window(view.rpc, sub, h_band, view.shape, margin=4 * f + 8)
    if win is None:
        return None
    r0, r1, c0, c1 = win
    r0, c0 = (r0 // f) * f, (c0 // f) * f
    r1 = min(view.shape[0], -(-r1 // f) * f)
    c1 = min(view.shape[1], -(-c1 // f) * f)
    if (r1 - r0) < 2 * f or (c1 - c0) < 2 * f:
        return None
    img = read_window(view, (r0, r1, c0, c1))
    if not np.isfinite(img).any():
        return None
    return downsample(img, f), (r0 // f, c0 // f)


def match_cells(
    views: Sequence[View],
    geom: LevelGeometry,
    cells: tuple[int, int, int, int],
    search: np.ndarray | None,
    h_range: tuple[float, float],
    params: DSMParams,
    details: dict | None = None,
) -> np.ndarray:
    """Heights and confidence of the level cells ``cells = (row0, row1,
    col0, col1)`` (a chunk plus its halo), matched together.

    ``search`` is ``(3, rows, cols)`` ``h_ref, lo, hi`` from the coarser
    level (:func:`tiledsm.match.pyramid.search_from_coarse`), or ``None``
    at the coarsest level (the whole ``h_range``, a horizontal sweep).
    ``details``, if given, is filled by
    :func:`~tiledsm.match.sgvll.match_block` (e.g. ``candidates``, the
    candidate heights of each cell; left empty when nothing is matched).

    Returns
    -------
    numpy.ndarray
        ``(2, rows, cols)`` float32: height (ellipsoidal metres, NaN =
        none) and confidence (winning ZNCC, 0..1).
    """
    from tiledsm.cluster import single_threaded_libraries
    from tiledsm.match.sgvll import match_block

    single_threaded_libraries()
    r0, r1, c0, c1 = cells
    sub = geom.grid.subgrid(r0, r1, c0, c1)
    out = np.full((2, r1 - r0, c1 - c0), np.nan, np.float32)
    if search is None:
        lo, hi, h_ref = float(h_range[0]), float(h_range[1]), None
        band = (lo, hi)
    else:
        h_ref, lo, hi = search
        if not np.isfinite(lo).any():
            return out
        band = (float(np.nanmin(lo)), float(np.nanmax(hi)))
        if params.search.relative_labels:
            # cells the coarser level gives nothing to search still get a
            # deterministic surface: their samples enter neighbours' windows
            h_ref = np.where(np.isfinite(h_ref), h_ref, np.float32(np.mean(h_range)))
        else:
            # the scene-wide lattice: one constant for every block, so chunks agree
            h_ref = np.full(h_ref.shape, np.float32(np.mean(h_range)), np.float32)
    f = geom.factor
    images, rpcs, windows = [], [], []
    for v in views:
        got = _level_image(v, sub, band, f)
        if got is None:
            return out  # a view does not see these cells
        images.append(got[0])
        windows.append(got[1])
        rpcs.append(v.rpc.scaled(1.0 / f) if f > 1 else v.rpc)
    g = geom.grid
    # speckles are removed afterwards over the whole level (despeckle), with
    # their own halo: the component sizes are then exact in any chunking
    kernel = dataclasses.replace(params.match, speckle_size=0)
    height, conf = match_block(
        images, rpcs, windows, sub.x, sub.y, sub.crs, lo, hi, kernel, step=geom.step, h_ref=h_ref,
        origin=(r0, c0), axes=(float(g.x[0]), float(g.y[0]), g.resolution, -g.resolution),
        pair_weights=geom.pair_weights, details=details,
    )
    out[0], out[1] = height, conf
    return out


def level_chunks(n: int, chunk: int, min_size: int) -> tuple[int, ...]:
    """Chunk sizes of one axis of ``n`` cells: ``chunk`` each, the last one
    merged into its neighbour when it would be smaller than ``min_size``
    (a halo must fit in every chunk)."""
    sizes = [chunk] * (n // chunk) + ([n % chunk] if n % chunk else [])
    if len(sizes) > 1 and sizes[-1] < min_size:
        last = sizes.pop()
        sizes[-1] += last
    return tuple(sizes)


def min_chunk(params: DSMParams) -> int:
    """Smallest chunk side a level is matched in: its halo must fit in a
    neighbour, and so must the coarser cells a task derives its search
    band from (:func:`coarse_blocks`: half a chunk deep)."""
    from tiledsm.match.pyramid import search_halo

    return max(params.halo(), 2 * (search_halo(params.search) + params.halo() // 2))


def level_layout(shape: tuple[int, int], chunk: int, params: DSMParams) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Chunks ``(rows, cols)`` a pyramid level of ``shape`` cells is
    matched in, for a grid chunked ``chunk``: a chunk smaller than the
    halos (:func:`min_chunk`) would be matched in larger ones (then
    rechunked to the grid's), as the work of a chunk grows with its halo."""
    floor = min_chunk(params)
    side = max(int(chunk), floor)
    return tuple(level_chunks(int(n), side, floor) for n in shape)


def chunk_window(chunks: tuple[int, ...], index: int, halo: int) -> tuple[int, int, int, int]:
    """``(start, stop, halo_start, halo_stop)`` of chunk ``index`` of an
    axis chunked as ``chunks``, the halo clipped to the axis."""
    start = sum(chunks[:index])
    stop = start + chunks[index]
    return start, stop, max(0, start - halo), min(sum(chunks), stop + halo)


def task_window(chunks: tuple[int, ...], index: int, params: DSMParams) -> tuple[int, int, int, int]:
    """``(start, stop, lo, hi)``: chunk ``index`` of an axis chunked as
    ``chunks`` and the cells ``[lo, hi)`` its matching task computes.

    A cell's aggregated cost depends only on the costs between the
    semi-global paths' restart lines around it (every ``path_period``
    cells of the whole grid), and a cost on the samples of its correlation
    window: the task reaches from the restart line at or before ``start``
    to the one at or after ``stop``, plus half a window, clipped to the
    axis. A chunk that starts and ends on restart lines (chunks of 512,
    period 64) is matched with only the window's few extra cells instead
    of a full halo of ``params.halo()`` on each side, with the same
    result. Without restarts (period 0) the halo is ``params.halo()``.
    """
    n = sum(chunks)
    start, stop, _, _ = chunk_window(chunks, index, 0)
    p = params.match.path_period
    if p > 0:
        half = params.match.window // 2
        lo, hi = (start // p) * p - half, -(-stop // p) * p + half
    else:
        lo, hi = start - params.halo(), stop + params.halo()
    lo, hi = max(0, lo), min(n, hi)
    if start - lo > params.halo() or hi - stop > params.halo():
        raise MatchingError(f"internal: task window {(lo, hi)} of chunk {(start, stop)} exceeds the halo {params.halo()}")
    return start, stop, lo, hi


def match_task(coarse, views, geom, chunks, h_range, params, coarsest: bool, block_id=None, details=None) -> np.ndarray:
    """One chunk of a level: match the cells of its :func:`task_window`,
    return the chunk.

    ``coarse`` is the coarser level's heights under the chunk, grown by
    :func:`coarse_depth` coarse cells (NaN beyond the grid;
    :func:`coarse_blocks`): the chunk's search band over its halo is
    derived here (:func:`~tiledsm.match.pyramid.search_from_coarse`), which
    spares the graph a second overlapped array. At the coarsest level it
    is a placeholder (the whole height range is searched). ``details``, if
    given, gets ``candidates``: the candidate heights of each cell of the
    chunk (0 where none was searched)."""
    from tiledsm.match.pyramid import search_from_coarse, search_halo

    halo = params.halo()  # the coarse blocks' reach, in finer cells (coarse_depth)
    r0, r1, hr0, hr1 = task_window(chunks[0], block_id[-2], params)
    c0, c1, hc0, hc1 = task_window(chunks[1], block_id[-1], params)
    search = None
    if not coarsest:
        depth = search_halo(params.search)
        # fine cells [r0 - halo, ...) of the band, then the halo clipped to the grid
        band = search_from_coarse(coarse, depth, params.refine_steps * geom.step, tuple(h_range), params.search)
        a, b = hr0 - (r0 - halo), hc0 - (c0 - halo)
        search = band[:, a : a + hr1 - hr0, b : b + hc1 - hc0]
        if search.shape[1:] != (hr1 - hr0, hc1 - hc0):
            raise MatchingError(f"internal: search block {search.shape} for cells {(hr0, hr1, hc0, hc1)}")
    found: dict | None = {} if details is not None else None
    res = match_cells(views, geom, (hr0, hr1, hc0, hc1), search, h_range, params, details=found)
    if details is not None:
        cand = found.get("candidates")
        details["candidates"] = (
            np.zeros((r1 - r0, c1 - c0), np.int32) if cand is None else cand[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
        )
    return res[:, r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]


def _overlap(x: da.Array, depth: dict[int, int]) -> da.Array:
    """Blocks of ``x`` grown by ``depth`` cells into their neighbours
    (nothing added at the array's edges); axes of one chunk need none."""
    depth = {ax: (d if len(x.chunks[ax]) > 1 else 0) for ax, d in depth.items()}
    return da.overlap.overlap(x, depth=depth, boundary="none", allow_rechunk=False)


def coarse_chunks(chunks, coarse_shape) -> tuple[tuple[int, ...], ...]:
    """The coarser level's cells under each finer chunk of ``chunks``, per
    axis: half of each chunk (coarse cell ``I`` covers finer cells ``2I,
    2I+1``), the last one taking the rest of ``coarse_shape``."""
    return tuple(
        tuple(n // 2 for n in ch[:-1]) + (nc - sum(n // 2 for n in ch[:-1]),)
        for ch, nc in zip(chunks, coarse_shape)
    )


def coarse_blocks(coarse: da.Array, chunks, depth: int) -> da.Array:
    """The coarser level's heights ``coarse`` as one block per finer chunk
    of ``chunks``: rechunked to half the finer chunks (coarse cell ``I``
    covers finer cells ``2I, 2I+1``), each block grown by ``depth`` coarse
    cells (NaN beyond the grid)."""
    c = coarse.rechunk(coarse_chunks(chunks, coarse.shape))
    padded = da.pad(c, depth, mode="constant", constant_values=np.nan)
    # da.pad adds the padding to the first and last chunks: same block layout
    padded = padded.rechunk(
        tuple(
            (ch[0] + depth,) + ch[1:-1] + (ch[-1] + depth,) if len(ch) > 1 else (ch[0] + 2 * depth,)
            for ch in c.chunks
        )
    )
    return _overlap(padded, {0: depth, 1: depth})


def despeckle_heights(block: np.ndarray, max_diff: float, min_size: int) -> np.ndarray:
    """``block`` (``(2, rows, cols)`` heights and confidence) with the
    height components of fewer than ``min_size`` cells set to NaN
    (:func:`~tiledsm.match.sgm.remove_speckles`); confidence unchanged."""
    from tiledsm.match.sgm import remove_speckles

    out = block.copy()
    out[0] = remove_speckles(block[0], max_diff, min_size)
    return out


def speckle_rule(geom: LevelGeometry, params: DSMParams) -> tuple[int, float]:
    """``(min_size, max_diff)`` of the speckle filter at ``geom``'s level:
    components of fewer than ``min_size`` cells are removed (none when it
    is <= 1), neighbours differing by at most ``max_diff`` metres are
    connected."""
    # the same ground area at every level: a coarse cell is 4**level cells
    # (a 16 m tower is 64 cells at level 2, a speckle at level 0)
    size = int(params.match.speckle_size) // 4**geom.level
    return size, params.match.speckle_max_diff(geom.grid.resolution, geom.step)


def despeckle(matched: da.Array, geom: LevelGeometry, params: DSMParams) -> da.Array:
    """``matched`` (heights, confidence) without the height components of
    fewer than ``params.match.speckle_size / 4**level`` cells (4-neighbours
    are connected when no steeper than ``speckle_slope``): isolated
    blunders.

    One ``map_overlap`` with a halo of that many cells: a component
    smaller than that lies entirely in a chunk's halo, and one that reaches
    the halo's edge has at least that many cells, so the result is exact in
    any chunking."""
    size, max_diff = speckle_rule(geom, params)
    if size <= 1:
        return matched
    chunks = matched.chunks
    # an axis no longer than the halo is taken whole (dask needs depth < size)
    short = {ax: -1 for ax in (1, 2) if matched.shape[ax] <= size}
    depth = {0: 0, **{ax: (0 if ax in short else size) for ax in (1, 2)}}
    out = da.map_overlap(
        despeckle_heights, matched.rechunk(short) if short else matched, depth=depth, boundary="none", trim=True,
        dtype=np.float32,
        max_diff=max_diff, min_size=size,
    )
    # map_overlap may have rechunked to fit a halo wider than a chunk
    return out.rechunk(chunks)


def level_array(views, geom: LevelGeometry, chunks, h_range, params: DSMParams, coarse: da.Array | None) -> da.Array:
    """Lazy ``(2, H, W)`` heights and confidence of one pyramid level,
    chunked as ``chunks``: one task per chunk, each matching the cells of
    its :func:`task_window` (searching around ``coarse``, the coarser
    level's heights, or the whole height range when ``None``) and
    returning the chunk; then :func:`despeckle`."""
    coarsest = coarse is None
    if coarsest:
        blocks = da.zeros((1, *geom.grid.shape), chunks=((1,), *chunks), dtype=np.uint8)
    else:
        blocks = coarse_blocks(coarse, chunks, coarse_depth(params))
    matched = da.map_blocks(
        match_task, blocks, views, geom, chunks, tuple(h_range), params, coarsest,
        chunks=((2,), *chunks), dtype=np.float32, name=f"match-L{geom.level}", new_axis=None if coarsest else 0,
    )
    return despeckle(matched, geom, params)


def coarse_depth(params: DSMParams) -> int:
    """Coarser cells a finer task reads around its chunk's half (see
    :func:`coarse_blocks`): the search band's support plus half the
    matching halo."""
    from tiledsm.match.pyramid import search_halo

    return search_halo(params.search) + params.halo() // 2


def _grid_centre_lonlat(grid: GroundGrid) -> tuple[float, float]:
    from pyproj import Transformer

    tr = Transformer.from_crs(grid.crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(float(np.mean(grid.x)), float(np.mean(grid.y)))
    return float(lon), float(lat)


def auto_levels(views: Sequence[View], grid: GroundGrid, h_range: tuple[float, float], params: DSMParams) -> int:
    """Pyramid levels so the coarsest sweep needs at most
    ``params.max_candidates`` heights (at most 5 levels)."""
    n = (h_range[1] - h_range[0]) / level_geometry(views, grid, 0, h_range, params).step
    levels = 1
    while n > params.max_candidates and levels < 5:
        n /= 2
        levels += 1
    return levels
