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
from tiledsm.match.sgvll import SGVLLParams

log = logging.getLogger(__name__)

__all__ = [
    "DSMParams",
    "View",
    "open_views",
    "scene_height_range",
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

    def __post_init__(self) -> None:
        if self.chunk < 32 or self.chunk % 2:
            # even chunks keep coarse and fine chunk corners aligned
            raise ValueError(f"DSMParams.chunk must be even and >= 32, got {self.chunk}")
        if self.levels is not None and self.levels < 1:
            raise ValueError(f"DSMParams.levels must be >= 1, got {self.levels}")

    def halo(self) -> int:
        """Halo in cells (even): enough aggregation context for the
        semi-global paths to carry information across the chunk border,
        plus the correlation window."""
        h = max(32, 2 * self.match.window)
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
    with the RPCs; the range is their 1st-99th percentile widened by
    ``params.height_margin``. With ``relative_correction`` the RPCs of views
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
def _level_grid(grid: GroundGrid, level: int) -> GroundGrid:
    """The grid of pyramid level ``level``: cells ``2**level`` times larger,
    same top-left corner, so coarse cell ``I`` covers fine cells ``2I, 2I+1``
    of the next finer level."""
    f = 2**level
    return GroundGrid(
        crs=grid.crs,
        x0=grid.x0,
        y0=grid.y0,
        resolution=grid.resolution * f,
        width=max(1, math.ceil(grid.width / f)),
        height=max(1, math.ceil(grid.height / f)),
        chunk=grid.chunk,
    )


def _level_step(views: Sequence[View], grid: GroundGrid, level: int, h_range, params: DSMParams) -> float:
    """Height step (metres) of a level: about ``step_px`` pixels of parallax
    in the level's images, measured at the grid centre. One step per level
    for the whole grid, so every chunk sweeps the same candidate lattice."""
    from tiledsm.match.sgvll import height_step

    lon, lat = _grid_centre_lonlat(grid)
    f = 2**level
    rpcs = [v.rpc.scaled(1.0 / f) if f > 1 else v.rpc for v in views]
    return float(height_step(rpcs, lon, lat, float(np.mean(h_range)), params.match))


def _match_chunk(
    views: Sequence[View],
    grid: GroundGrid,
    window: tuple[int, int, int, int],
    level: int,
    halo: int,
    h_range: tuple[float, float],
    step: float,
    params: DSMParams,
    coarse: np.ndarray | None,
) -> np.ndarray:
    """One task: heights and confidence of grid cells ``window`` (row0, row1,
    col0, col1) of the level grid ``grid``.

    ``coarse`` holds the coarser level's heights over the cells covering
    this chunk plus halo (coarse cell ``I`` = fine cells ``2I, 2I+1``
    counted from the halo's first row/col, which is even), or ``None`` at
    the coarsest level.

    Returns
    -------
    numpy.ndarray
        ``(2, rows, cols)`` float32: height (m, ellipsoidal; NaN = none) and
        confidence (winning ZNCC, 0..1).
    """
    from tiledsm.cluster import single_threaded_libraries
    from tiledsm.geometry.footprint import image_window
    from tiledsm.match.sgvll import downsample, match_block, refine_search

    single_threaded_libraries()
    r0, r1, c0, c1 = window
    out = np.full((2, r1 - r0, c1 - c0), np.nan, np.float32)
    hr0, hr1 = max(0, r0 - halo), min(grid.height, r1 + halo)
    hc0, hc1 = max(0, c0 - halo), min(grid.width, c1 + halo)
    sub = grid.subgrid(hr0, hr1, hc0, hc1)
    shape = (sub.height, sub.width)
    if coarse is None:
        lo = np.full(shape, h_range[0], np.float32)
        hi = np.full(shape, h_range[1], np.float32)
        h_ref = None
    else:
        lo, hi, h_ref = refine_search(coarse, 2, shape, params.refine_steps * step, h_range[0], h_range[1])
    f = 2**level
    images, rpcs = [], []
    for v in views:
        win = image_window(v.rpc, sub, (float(np.min(lo)), float(np.max(hi))), v.shape, margin=4 * f + 8)
        if win is None:
            return out  # the ground chunk is not seen by this view
        img = read_window(v, win)
        if not np.isfinite(img).any():
            return out  # nothing but nodata
        rpc = v.rpc.cropped(win[0], win[2])
        if f > 1:
            img = downsample(img, f)
            rpc = rpc.scaled(1.0 / f)
        images.append(img)
        rpcs.append(rpc)
    height, conf = match_block(images, rpcs, None, sub.x, sub.y, sub.crs, lo, hi, params.match, step=step, h_ref=h_ref)
    out[0] = height[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
    out[1] = conf[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
    return out


def _grid_centre_lonlat(grid: GroundGrid) -> tuple[float, float]:
    from pyproj import Transformer

    tr = Transformer.from_crs(grid.crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(float(np.mean(grid.x)), float(np.mean(grid.y)))
    return float(lon), float(lat)


@dataclass(frozen=True)
class _Level:
    """The tasks of one pyramid level: ``blocks[i][j]`` is the delayed
    ``(2, rows, cols)`` result of chunk ``(i, j)``, whose cells are
    ``windows[i][j] = (row0, row1, col0, col1)`` of the level grid."""

    blocks: list
    windows: list

    def parts(self, rows: tuple[int, int], cols: tuple[int, int]) -> list:
        """``(block, (row0, col0))`` of every chunk overlapping the cells
        ``rows x cols`` (half-open)."""
        out = []
        for line_b, line_w in zip(self.blocks, self.windows):
            for b, (r0, r1, c0, c1) in zip(line_b, line_w):
                if r0 < rows[1] and r1 > rows[0] and c0 < cols[1] and c1 > cols[0]:
                    out.append((b, (r0, c0)))
        return out


def _assemble(parts: list, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """Heights (band 0) of the cells ``rows x cols`` from computed chunks
    ``(array, (row0, col0))``; NaN where no chunk covers a cell."""
    out = np.full((rows[1] - rows[0], cols[1] - cols[0]), np.nan, np.float32)
    for arr, (r0, c0) in parts:
        h = arr[0]
        a0, a1 = max(rows[0], r0), min(rows[1], r0 + h.shape[0])
        b0, b1 = max(cols[0], c0), min(cols[1], c0 + h.shape[1])
        if a1 > a0 and b1 > b0:
            out[a0 - rows[0] : a1 - rows[0], b0 - cols[0] : b1 - cols[0]] = h[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0]
    return out


def _match_chunk_from_parts(views, grid, window, level, halo, h_range, step, params, parts, rows, cols):
    """:func:`_match_chunk` with the coarser heights given as computed chunks."""
    coarse = None if parts is None else _assemble(parts, rows, cols)
    return _match_chunk(views, grid, window, level, halo, h_range, step, params, coarse)


def _level_tasks(
    views: Sequence[View],
    grid: GroundGrid,
    level: int,
    h_range: tuple[float, float],
    params: DSMParams,
    coarse: _Level | None,
) -> _Level:
    """The tasks of one pyramid level, one per chunk of ``grid``.

    A chunk of a finer level depends only on the coarser-level chunks under
    its footprint + halo, passed as the coarser tasks themselves (not as a
    slice of a dask array: ``dask.delayed`` would optimise such a slice into
    each dependant and recompute the coarser chunk once per finer chunk).
    """
    halo = params.halo()
    step = _level_step(views, grid, level, h_range, params)
    task = dask.delayed(_match_chunk_from_parts, pure=True)
    nby, nbx = grid.numblocks
    blocks, windows = [], []
    for i in range(nby):
        line_b, line_w = [], []
        for j in range(nbx):
            r0, r1, c0, c1 = grid.block_window(i, j)
            parts = rows = cols = None
            if coarse is not None:
                hr0, hr1 = max(0, r0 - halo), min(grid.height, r1 + halo)
                hc0, hc1 = max(0, c0 - halo), min(grid.width, c1 + halo)
                rows, cols = (hr0 // 2, -(-hr1 // 2)), (hc0 // 2, -(-hc1 // 2))
                parts = coarse.parts(rows, cols)
            d = task(views, grid, (r0, r1, c0, c1), level, halo, h_range, step, params, parts, rows, cols)
            line_b.append(d)
            line_w.append((r0, r1, c0, c1))
        blocks.append(line_b)
        windows.append(line_w)
    return _Level(blocks, windows)


def _level_array(level: _Level) -> da.Array:
    """Lazy ``(2, height, width)`` array of a level's tasks."""
    return da.block(
        [
            [da.from_delayed(b, shape=(2, r1 - r0, c1 - c0), dtype=np.float32) for b, (r0, r1, c0, c1) in zip(lb, lw)]
            for lb, lw in zip(level.blocks, level.windows)
        ]
    )


def auto_levels(views: Sequence[View], grid: GroundGrid, h_range: tuple[float, float], params: DSMParams) -> int:
    """Pyramid levels so the coarsest sweep needs at most
    ``params.max_candidates`` heights (at most 5 levels)."""
    n = (h_range[1] - h_range[0]) / _level_step(views, grid, 0, h_range, params)
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

    Returns
    -------
    xarray.Dataset
        ``height`` (float32 metres, WGS84 ellipsoidal, NaN = no height) and
        ``confidence`` (0..1), dims ``(y, x)``, dask-backed, CRS written.
    """
    if h_range[1] <= h_range[0]:
        raise MatchingError(f"empty height range {h_range}")
    tasks = None
    levels = params.levels or auto_levels(views, grid, h_range, params)
    for level in range(levels - 1, -1, -1):
        tasks = _level_tasks(views, _level_grid(grid, level), level, h_range, params, tasks)
    arr = _level_array(tasks)
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
        views=[v.path for v in views], height_range_m=list(h_range), levels=levels, params=_params_dict(params)
    )
    return ds


def _params_dict(params: DSMParams) -> str:
    import json

    return json.dumps(dataclasses.asdict(params))


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
    t0 = time.perf_counter()
    if params.height_range is None:
        h_range, views, report = scene_height_range(views, params)
    else:
        h_range, report = tuple(params.height_range), {"height_range_m": list(params.height_range)}
        if params.relative_correction:
            # the range is given, but the relative pointing error still needs tie points;
            # a given range is often the answer to tie points failing, so failing here is not fatal
            try:
                _, views, tie_report = scene_height_range(views, params)
                report.update({k: v for k, v in tie_report.items() if k != "height_range_m"})
            except MatchingError as exc:
                log.warning("no relative correction: %s", exc)
                report["relative_correction"] = f"not applied: {exc}"
    report["preparation_s"] = time.perf_counter() - t0
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
