"""DSM stage: images with RPCs -> a tiled, seamless DSM on a ground grid.

Dense matching happens in object space (semi-global vertical line locus,
:mod:`tiledsm.match.sgvll`): every dask task owns one chunk of the final
ground grid plus a halo, reads only the image windows its footprint needs,
matches, trims the halo and hands back its chunk. Chunks of neighbouring
tasks share one grid, so the mosaic has no seams by construction.

Coarse to fine: level ``L-1`` (coarsest, ground resolution ``res * 2**(L-1)``)
searches the whole scene height range; each finer level searches a few
height steps around the upsampled coarser DSM, per cell.

Conventions: heights are metres above the WGS84 ellipsoid (the RPCs'),
unless a geoid grid is given for the output; NaN means "no height".
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import dask
import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.errors import MatchingError, NoOverlapError, TiledsmError
from tiledsm.geometry import RPC
from tiledsm.geometry.grid import GroundGrid
from tiledsm.match.pyramid import SearchParams
from tiledsm.match.sgvll import SGVLLParams

log = logging.getLogger(__name__)

__all__ = [
    "DSMParams",
    "View",
    "open_views",
    "scene_height_range",
    "prepare_views",
    "level_layout",
    "min_chunk",
    "default_grid",
    "dsm_from_views",
    "dsm_from_pair",
    "heights_above_geoid",
    "footprint_mask",
]


@dataclass(frozen=True)
class DSMParams:
    """Parameters of the DSM stage.

    Attributes
    ----------
    resolution : float or None
        Ground cell size, metres; ``None`` takes the mean GSD of the views.
    crs : str or None
        CRS of the default grid (when no grid is given; projected, metres);
        ``None`` takes the UTM zone of the scene centre.
    chunk : int
        Chunk side of the output grid, cells.
    levels : int or None
        Pyramid levels (1 = full resolution only). ``None`` chooses: one
        level while the full-resolution sweep needs at most
        ``max_candidates`` heights, and one more level for each doubling
        beyond (measured on synthetic truth, a coarse level costs
        completeness next to buildings, so it is used only when the search
        is wide).
    max_candidates : int
        See ``levels``.
    height_range : (float, float) or None
        Scene height range (ellipsoidal metres); ``None`` estimates it from
        tie points.
    height_margin : float
        Metres added on both sides of the tie-point height range.
    refine_steps : int
        Height steps searched on each side of the upsampled coarser DSM at
        the finer levels.
    relative_correction : bool
        Correct the relative pointing error of views 2.. by a translation
        estimated from tie points.
    match : SGVLLParams
        Matching parameters (window, penalties, thresholds).
    search : SearchParams
        How a coarser level's DSM becomes a finer level's search band.
    """

    resolution: float | None = None
    crs: str | None = None
    chunk: int = 512
    levels: int | None = None
    max_candidates: int = 192
    height_range: tuple[float, float] | None = None
    height_margin: float = 10.0
    refine_steps: int = 4
    relative_correction: bool = True
    match: SGVLLParams = field(default_factory=SGVLLParams)
    search: SearchParams = field(default_factory=SearchParams)

    def __post_init__(self) -> None:
        if self.chunk < 32 or self.chunk % 2:
            # even chunks keep coarse and fine chunk corners aligned
            raise ValueError(f"DSMParams.chunk must be even and >= 32, got {self.chunk}")
        if self.levels is not None and self.levels < 1:
            raise ValueError(f"DSMParams.levels must be >= 1, got {self.levels}")

    def halo(self) -> int:
        """Halo in cells (even) of a matching task: the semi-global paths'
        restart period (:attr:`~tiledsm.match.sgvll.SGVLLParams.path_period`,
        which makes the aggregation exact in every chunking), and at least
        twice the correlation window."""
        h = max(2 * self.match.window, self.match.path_period)
        return h + h % 2


@dataclass(frozen=True)
class View:
    """One image of the acquisition: its file, camera and size.

    ``rpc`` is the (possibly corrected) camera in GDAL pixel convention.
    """

    path: str
    rpc: RPC
    shape: tuple[int, int]
    nodata: float | None = None


def open_views(paths: Sequence[str | Path], rpcs: Sequence[str | Path | None] | None = None) -> list[View]:
    """Read cameras and sizes of the views (not their pixels)."""
    import rasterio

    from tiledsm.errors import InputFileError
    from tiledsm.geometry.rpc_io import find_camera

    if len(paths) < 2:
        raise TiledsmError(f"a DSM needs at least two views, got {len(paths)}")
    rpcs = list(rpcs) if rpcs is not None else [None] * len(paths)
    views = []
    for p, r in zip(paths, rpcs):
        p = Path(p)
        if not p.exists():
            raise InputFileError(f"{p}: no such file")
        camera, _ = find_camera(p, r)
        try:
            with rasterio.open(p) as ds:
                views.append(View(str(p), camera, (ds.height, ds.width), ds.nodata))
        except rasterio.errors.RasterioIOError as exc:
            raise InputFileError(f"{p}: not a readable raster ({exc})") from exc
    return views


def read_window(view: View, window: tuple[int, int, int, int]) -> np.ndarray:
    """Pixels of ``view`` in ``(row0, row1, col0, col1)`` as float32, NaN nodata."""
    import rasterio
    from rasterio.windows import Window

    r0, r1, c0, c1 = window
    with rasterio.open(view.path) as ds:
        arr = ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
    return arr.astype(np.float32).filled(np.nan)


def _overview(view: View, factor: int) -> np.ndarray:
    """Whole view downsampled by ``factor`` (area averaging), float32.

    Read with GDAL's decimated read so a huge scene never sits in memory at
    full resolution.
    """
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(view.path) as ds:
        h, w = max(1, ds.height // factor), max(1, ds.width // factor)
        arr = ds.read(1, out_shape=(h, w), masked=True, resampling=Resampling.average)
    return arr.astype(np.float32).filled(np.nan)


def scene_height_range(views: Sequence[View], params: DSMParams) -> tuple[tuple[float, float], list[View], dict]:
    """Height range of the scene and relatively corrected views, from tie points.

    Tie points are matched on overviews (at most ~1500 px a side), triangulated
    with the RPCs; the range runs from the lowest to the highest tie point
    that its neighbours confirm, widened by ``params.height_margin`` and
    kept inside the RPCs' validity range
    (:func:`~tiledsm.match.tiepoints.height_range_from_tiepoints`: a tower's
    few roof points count, a lone mismatch does not). With ``relative_correction`` the RPCs of views
    2.. are translated in image space to remove the mean reprojection
    residual (the relative pointing error).

    Returns
    -------
    (h_min, h_max), views, report
    """
    from tiledsm.match.tiepoints import height_range_from_tiepoints, match_tiepoints, relative_correction

    report: dict = {}
    factor = max(1, int(math.ceil(max(max(v.shape) for v in views) / 1500)))
    ref = views[0]
    ref_img = _overview(ref, factor)
    corrected = [ref]
    ranges = []
    for i, other in enumerate(views[1:], start=1):
        p1, p2 = match_tiepoints(ref_img, _overview(other, factor))
        # overview pixel coordinates (GDAL convention) -> full image
        p1, p2 = p1 * factor, p2 * factor
        if len(p1) < 10:
            raise MatchingError(
                f"only {len(p1)} tie points between {ref.path} and {other.path}: "
                "the images may not overlap; give a height range explicitly"
            )
        rpc2 = other.rpc
        if params.relative_correction:
            drow, dcol = relative_correction(ref.rpc, other.rpc, p1, p2)
            rpc2 = other.rpc.replace(line_off=other.rpc.line_off + drow, samp_off=other.rpc.samp_off + dcol)
            report[f"relative_correction_view{i}_px"] = {"drow": float(drow), "dcol": float(dcol)}
        lo, hi = height_range_from_tiepoints(ref.rpc, rpc2, p1, p2, margin=params.height_margin)
        ranges.append((lo, hi))
        report[f"tiepoints_view{i}"] = int(len(p1))
        corrected.append(dataclasses.replace(other, rpc=rpc2))
    h_range = (min(r[0] for r in ranges), max(r[1] for r in ranges))
    report["height_range_m"] = list(h_range)
    return h_range, corrected, report


def default_grid(views: Sequence[View], h_range: tuple[float, float], params: DSMParams) -> GroundGrid:
    """Ground grid over the overlap of all views, in ``params.crs`` (default:
    the UTM zone of the scene centre), cells of ``params.resolution``."""
    from tiledsm.geometry.footprint import overlap_lonlat_bounds
    from tiledsm.geometry.grid import GroundGrid, utm_crs

    lon0, lat0, lon1, lat1 = overlap_lonlat_bounds(views[0].rpc, views[0].shape, views[1].rpc, views[1].shape, h_range)
    for v in views[2:]:
        a = overlap_lonlat_bounds(views[0].rpc, views[0].shape, v.rpc, v.shape, h_range)
        lon0, lat0, lon1, lat1 = max(lon0, a[0]), max(lat0, a[1]), min(lon1, a[2]), min(lat1, a[3])
    if lon0 >= lon1 or lat0 >= lat1:
        raise NoOverlapError("the views have no ground in common: " + ", ".join(v.path for v in views))
    crs = params.crs or utm_crs((lon0 + lon1) / 2, (lat0 + lat1) / 2)
    res = params.resolution or _mean_gsd(views, sum(h_range) / 2)
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    # the densified lon/lat box: its edges are curved in a projected CRS
    t = np.linspace(0.0, 1.0, 17)
    lons = np.concatenate([lon0 + t * (lon1 - lon0), np.full(17, lon1), lon0 + t * (lon1 - lon0), np.full(17, lon0)])
    lats = np.concatenate([np.full(17, lat0), lat0 + t * (lat1 - lat0), np.full(17, lat1), lat0 + t * (lat1 - lat0)])
    xs, ys = tr.transform(lons, lats)
    bounds = (min(xs), min(ys), max(xs), max(ys))
    return GroundGrid.from_bounds(crs, bounds, res, chunk=params.chunk)


def _mean_gsd(views: Sequence[View], h: float) -> float:
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    gsds = []
    for v in views:
        r, c = v.shape[0] / 2, v.shape[1] / 2
        lon, lat = v.rpc.localize(np.array([r, r + 1, r]), np.array([c, c, c + 1]), h)
        gsds.append(geod.inv(lon[0], lat[0], lon[1], lat[1])[2])
        gsds.append(geod.inv(lon[0], lat[0], lon[2], lat[2])[2])
    return float(np.round(np.mean(gsds), 3))


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


def level_geometry(views: Sequence[View], grid: GroundGrid, level: int, h_range, params: DSMParams) -> LevelGeometry:
    """The :class:`LevelGeometry` of pyramid level ``level`` of ``grid``."""
    from tiledsm.match.sgvll import height_step, pair_weights

    lgrid = level_grid(grid, level)
    lon, lat = _grid_centre_lonlat(lgrid)
    f = 2**level
    rpcs = [v.rpc.scaled(1.0 / f) if f > 1 else v.rpc for v in views]
    h = float(np.mean(h_range))
    step = float(height_step(rpcs, lon, lat, h, params.match))
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
) -> np.ndarray:
    """Heights and confidence of the level cells ``cells = (row0, row1,
    col0, col1)`` (a chunk plus its halo), matched together.

    ``search`` is ``(3, rows, cols)`` ``h_ref, lo, hi`` from the coarser
    level (:func:`tiledsm.match.pyramid.search_from_coarse`), or ``None``
    at the coarsest level (the whole ``h_range``, a horizontal sweep).

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
        # cells the coarser level gives nothing to search still get a
        # deterministic surface: their samples enter neighbours' windows
        h_ref = np.where(np.isfinite(h_ref), h_ref, np.float32(np.mean(h_range)))
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
        pair_weights=geom.pair_weights,
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


def _windows(chunks: tuple[int, ...], index: int, halo: int) -> tuple[int, int, int, int]:
    """``(start, stop, halo_start, halo_stop)`` of chunk ``index`` of an
    axis chunked as ``chunks``, the halo clipped to the axis."""
    start = sum(chunks[:index])
    stop = start + chunks[index]
    return start, stop, max(0, start - halo), min(sum(chunks), stop + halo)


def _match_task(coarse, views, geom, chunks, halo, h_range, params, coarsest: bool, block_id=None) -> np.ndarray:
    """One chunk of a level: match it plus its halo, return the chunk.

    ``coarse`` is the coarser level's heights under the chunk, grown by
    ``search_halo + halo / 2`` coarse cells (NaN beyond the grid;
    :func:`coarse_blocks`): the chunk's search band over its halo is
    derived here (:func:`~tiledsm.match.pyramid.search_from_coarse`), which
    spares the graph a second overlapped array. At the coarsest level it
    is a placeholder (the whole height range is searched)."""
    from tiledsm.match.pyramid import search_from_coarse, search_halo

    r0, r1, hr0, hr1 = _windows(chunks[0], block_id[-2], halo)
    c0, c1, hc0, hc1 = _windows(chunks[1], block_id[-1], halo)
    search = None
    if not coarsest:
        depth = search_halo(params.search)
        # fine cells [r0 - halo, ...) of the band, then the halo clipped to the grid
        band = search_from_coarse(coarse, depth, params.refine_steps * geom.step, tuple(h_range), params.search)
        a, b = hr0 - (r0 - halo), hc0 - (c0 - halo)
        search = band[:, a : a + hr1 - hr0, b : b + hc1 - hc0]
        if search.shape[1:] != (hr1 - hr0, hc1 - hc0):
            raise MatchingError(f"internal: search block {search.shape} for cells {(hr0, hr1, hc0, hc1)}")
    res = match_cells(views, geom, (hr0, hr1, hc0, hc1), search, h_range, params)
    return res[:, r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]


def _overlap(x: da.Array, depth: dict[int, int]) -> da.Array:
    """Blocks of ``x`` grown by ``depth`` cells into their neighbours
    (nothing added at the array's edges); axes of one chunk need none."""
    depth = {ax: (d if len(x.chunks[ax]) > 1 else 0) for ax, d in depth.items()}
    return da.overlap.overlap(x, depth=depth, boundary="none", allow_rechunk=False)


def coarse_blocks(coarse: da.Array, chunks, depth: int) -> da.Array:
    """The coarser level's heights ``coarse`` as one block per finer chunk
    of ``chunks``: rechunked to half the finer chunks (coarse cell ``I``
    covers finer cells ``2I, 2I+1``), each block grown by ``depth`` coarse
    cells (NaN beyond the grid)."""
    half = tuple(
        tuple(n // 2 for n in ch[:-1]) + (nc - sum(n // 2 for n in ch[:-1]),)
        for ch, nc in zip(chunks, coarse.shape)
    )
    c = coarse.rechunk(half)
    padded = da.pad(c, depth, mode="constant", constant_values=np.nan)
    # da.pad adds the padding to the first and last chunks: same block layout
    padded = padded.rechunk(
        tuple(
            (ch[0] + depth,) + ch[1:-1] + (ch[-1] + depth,) if len(ch) > 1 else (ch[0] + 2 * depth,)
            for ch in c.chunks
        )
    )
    return _overlap(padded, {0: depth, 1: depth})


def _despeckle_heights(block: np.ndarray, max_diff: float, min_size: int) -> np.ndarray:
    from tiledsm.match.sgm import remove_speckles

    out = block.copy()
    out[0] = remove_speckles(block[0], max_diff, min_size)
    return out


def despeckle(matched: da.Array, geom: LevelGeometry, params: DSMParams) -> da.Array:
    """``matched`` (heights, confidence) without the height components of
    fewer than ``params.match.speckle_size / 4**level`` cells (4-neighbours
    are connected when no steeper than ``speckle_slope``): isolated
    blunders.

    One ``map_overlap`` with a halo of that many cells: a component
    smaller than that lies entirely in a chunk's halo, and one that reaches
    the halo's edge has at least that many cells, so the result is exact in
    any chunking."""
    # the same ground area at every level: a coarse cell is 4**level cells
    # (a 16 m tower is 64 cells at level 2, a speckle at level 0)
    size = int(params.match.speckle_size) // 4**geom.level
    if size <= 1:
        return matched
    chunks = matched.chunks
    # an axis no longer than the halo is taken whole (dask needs depth < size)
    short = {ax: -1 for ax in (1, 2) if matched.shape[ax] <= size}
    depth = {0: 0, **{ax: (0 if ax in short else size) for ax in (1, 2)}}
    out = da.map_overlap(
        _despeckle_heights, matched.rechunk(short) if short else matched, depth=depth, boundary="none", trim=True,
        dtype=np.float32,
        max_diff=params.match.speckle_max_diff(geom.grid.resolution, geom.step), min_size=size,
    )
    # map_overlap may have rechunked to fit a halo wider than a chunk
    return out.rechunk(chunks)


def level_array(views, geom: LevelGeometry, chunks, h_range, params: DSMParams, coarse: da.Array | None) -> da.Array:
    """Lazy ``(2, H, W)`` heights and confidence of one pyramid level,
    chunked as ``chunks``: one task per chunk, each matching its chunk plus
    ``params.halo()`` cells (searching around ``coarse``, the coarser
    level's heights, or the whole height range when ``None``) and
    returning the chunk; then :func:`despeckle`."""
    from tiledsm.match.pyramid import search_halo

    halo = params.halo()
    coarsest = coarse is None
    if coarsest:
        blocks = da.zeros((1, *geom.grid.shape), chunks=((1,), *chunks), dtype=np.uint8)
    else:
        blocks = coarse_blocks(coarse, chunks, search_halo(params.search) + halo // 2)
    matched = da.map_blocks(
        _match_task, blocks, views, geom, chunks, halo, tuple(h_range), params, coarsest,
        chunks=((2,), *chunks), dtype=np.float32, name=f"match-L{geom.level}", new_axis=None if coarsest else 0,
    )
    return despeckle(matched, geom, params)


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


def dsm_from_views(
    views: Sequence[View],
    grid: GroundGrid,
    h_range: tuple[float, float],
    params: DSMParams = DSMParams(),
) -> xr.Dataset:
    """Lazy DSM of ``views`` on ``grid`` (coarse to fine).

    Each pyramid level is a dask array on its own grid; a finer level is one
    ``map_blocks`` over its grid's chunks (plus halo) with the search band
    derived from the coarser level inside each task
    (:func:`level_array`). Every halo is derived from the parameters, so
    the result does not depend on the chunking.

    Returns
    -------
    xarray.Dataset
        ``height`` (float32 metres, WGS84 ellipsoidal, NaN = no height) and
        ``confidence`` (0..1), dims ``(y, x)``, dask-backed, CRS written.
    """
    import rioxarray  # noqa: F401  (registers .rio)

    if h_range[1] <= h_range[0]:
        raise MatchingError(f"empty height range {h_range}")
    levels = params.levels or auto_levels(views, grid, h_range, params)
    arr = None
    for level in range(levels - 1, -1, -1):
        geom = level_geometry(views, grid, level, h_range, params)
        chunks = level_layout(geom.grid.shape, grid.chunk, params)
        arr = level_array(views, geom, chunks, h_range, params, None if arr is None else arr[0])
    arr = arr.rechunk(((2,), *grid.chunks))
    # the finest level is on `grid` itself; its chunks are the grid's
    ds = xr.Dataset(
        {
            "height": (("y", "x"), arr[0]),
            "confidence": (("y", "x"), arr[1]),
        },
        coords={"y": grid.y, "x": grid.x},
    )
    ds["height"].attrs.update(units="m", long_name="height above the WGS84 ellipsoid", _FillValue=np.nan)
    ds["confidence"].attrs.update(units="1", long_name="matching confidence")
    ds = ds.rio.write_crs(grid.crs).rio.write_transform(grid.transform)
    ds.attrs.update(
        views=[v.path for v in views], height_range_m=list(h_range), levels=levels, params=_params_dict(params),
        fingerprint=json.dumps(dsm_fingerprint(views, grid, h_range, levels, params), sort_keys=True),
    )
    return ds


def dsm_fingerprint(views: Sequence[View], grid: GroundGrid, h_range, levels: int, params: DSMParams) -> dict:
    """Everything that determines the DSM, as plain JSON
    (:func:`tiledsm.provenance.fingerprint`): each input's identity (path,
    size, sampled content hash), the RPCs actually used (after relative
    correction), the grid, height range, levels, every parameter, and the
    package version and code. A stored DSM is resumed only under the same
    fingerprint."""
    from tiledsm.provenance import fingerprint, input_identity

    return fingerprint(
        inputs=[input_identity(v.path) for v in views],
        rpcs=[v.rpc for v in views],
        grid={"crs": str(grid.crs), "x0": grid.x0, "y0": grid.y0, "resolution": grid.resolution,
              "width": grid.width, "height": grid.height, "chunk": grid.chunk},
        height_range=list(h_range),
        levels=levels,
        params=dataclasses.asdict(params),
    )


def _params_dict(params: DSMParams) -> str:
    import json

    return json.dumps(dataclasses.asdict(params))


def prepare_views(views: Sequence[View], params: DSMParams) -> tuple[tuple[float, float], list[View], dict]:
    """Height range, relatively corrected views and report of a DSM run,
    before its graph is built.

    Tie points give the range unless ``params.height_range`` is set; the
    relative correction of views 2.. is applied when
    ``params.relative_correction`` (with a given range a failure of the tie
    points is only logged: a given range is often the answer to it, and the
    tie points' own range is reported as ``tiepoint_height_range_m``).

    Returns
    -------
    (hmin, hmax), views, report
        Ellipsoidal metres; the views as matched; tie points, correction and
        ``preparation_s``.
    """
    t0 = time.perf_counter()
    if params.height_range is None:
        h_range, views, report = scene_height_range(views, params)
    else:
        h_range, report = tuple(params.height_range), {"height_range_m": list(params.height_range)}
        if params.relative_correction:
            try:
                _, views, tie_report = scene_height_range(views, params)
                report.update({k: v for k, v in tie_report.items() if k != "height_range_m"})
                report["tiepoint_height_range_m"] = tie_report["height_range_m"]
            except MatchingError as exc:
                log.warning("no relative correction: %s", exc)
                report["relative_correction"] = f"not applied: {exc}"
    report["preparation_s"] = time.perf_counter() - t0
    return (float(h_range[0]), float(h_range[1])), list(views), report


def dsm_from_pair(
    left: str | Path,
    right: str | Path,
    *more: str | Path,
    rpcs: Sequence[str | Path | None] | None = None,
    grid: GroundGrid | None = None,
    params: DSMParams = DSMParams(),
) -> tuple[xr.Dataset, dict]:
    """DSM of two (or more) images with RPCs; lazy.

    ``rpcs`` optionally gives each image's RPC file (``None`` entries: the
    camera is found in the image or a sidecar). Returns the lazy dataset of
    :func:`dsm_from_views` and a report (tie points, height range, relative
    correction, grid).
    """
    views = open_views([left, right, *more], rpcs)
    h_range, views, report = prepare_views(views, params)
    if grid is None:
        grid = default_grid(views, h_range, params)
    report["grid"] = {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height, "chunk": grid.chunk}
    return dsm_from_views(views, grid, h_range, params), report


# ------------------------------------------------------------------ products
def _geoid_block(height: np.ndarray, x: np.ndarray, y: np.ndarray, crs: str, geoid: str, block_info=None) -> np.ndarray:
    from tiledsm.geometry.footprint import to_lonlat
    from tiledsm.geometry.geoid import geoid_height

    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    X, Y = np.meshgrid(x[c0:c1], y[r0:r1])
    lon, lat = to_lonlat(crs, X, Y)
    return (height - geoid_height(lon, lat, geoid)).astype(np.float32)


def heights_above_geoid(ds: xr.Dataset, geoid: str | Path) -> xr.Dataset:
    """The DSM with heights above the geoid of ``geoid`` instead of the
    WGS84 ellipsoid: ``H = h - N(lon, lat)``, chunk by chunk (lazy).

    Parameters
    ----------
    ds : xarray.Dataset
        Output of :func:`dsm_from_views` (``height`` in ellipsoidal metres,
        CRS written).
    geoid : path
        Geoid grid read by GDAL, e.g. EGM96 ``egm96_15.gtx``
        (see :mod:`tiledsm.geometry.geoid`).

    Raises
    ------
    InputFileError
        The grid is missing or unreadable (checked before anything runs).
    """
    from tiledsm.geometry.geoid import _load

    geoid = str(Path(geoid))
    _load(geoid)  # fail now, not inside a task
    h = ds["height"]
    data = da.map_blocks(
        _geoid_block, h.data, x=h.x.values, y=h.y.values, crs=ds.rio.crs.to_string(), geoid=geoid, dtype=np.float32
    )
    out = ds.copy()
    out["height"] = h.copy(data=data)
    if "fingerprint" in ds.attrs:
        from tiledsm.provenance import input_identity

        fp = json.loads(ds.attrs["fingerprint"])
        fp["geoid"] = input_identity(geoid)
        out.attrs["fingerprint"] = json.dumps(fp, sort_keys=True)
    out["height"].attrs.update(long_name=f"height above the geoid ({Path(geoid).name})", vertical_datum=Path(geoid).name)
    out.attrs["vertical_datum"] = f"geoid {Path(geoid).name}"
    return out


def footprint_mask(grid: GroundGrid, views: Sequence[View], height: float, step: int = 1) -> np.ndarray:
    """Cells of ``grid`` (every ``step``-th row and column) whose centre at
    ``height`` (ellipsoidal metres) projects inside every view.

    This is where a DSM can have heights at all: completeness is measured
    inside it.
    """
    from tiledsm.geometry.footprint import to_lonlat

    X, Y = np.meshgrid(grid.x[::step], grid.y[::step])
    lon, lat = to_lonlat(grid.crs, X, Y)
    inside = np.ones(X.shape, bool)
    for v in views:
        r, c = v.rpc.project(lon, lat, height)
        inside &= (r >= 0) & (r < v.shape[0]) & (c >= 0) & (c < v.shape[1])
    return inside
