"""The views of a DSM: images with their cameras, windows read from them,
their overviews, the scene's height range from tie points, the default
ground grid, and which cells every view sees (:func:`footprint_mask`)."""

from __future__ import annotations

import dataclasses
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from tiledsm.errors import MatchingError, NoOverlapError, TiledsmError
from tiledsm.geometry import RPC
from tiledsm.geometry.grid import GroundGrid
from tiledsm.dsm.params import DSMParams

#: longest side of the overviews tie points are matched on, pixels. SIFT's scale
#: space holds 11 float32 copies of the twice-upsampled overview in its first
#: octave (a third more in the others): measured, the process peaks 0.45 GiB
#: higher while it matches 1366 px overviews and 0.26 GiB at 1024 px. On the
#: 4096² synthetic scene, 1024 px overviews (this cap) instead of 1366 (1500)
#: gave 1101 tie points (969), a relative correction of 0.036 px (0.068; the
#: cameras are exact) and the same height range within 0.7 m. Images up to this
#: size (the s2p pair: 1102 px) are matched at full resolution.
TIEPOINT_OVERVIEW_PX = 1200

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
    from tiledsm.io.cameras import find_camera

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


#: this thread's open views: path -> (file identity, dataset)
_OPEN = threading.local()


def _dataset(path: str):
    """A rasterio dataset of ``path`` kept open by this thread.

    A task's window overlaps its neighbours' (halos, the levels of one
    area), and GDAL keeps decoded tiles per open dataset: a thread that
    keeps its views open reads such tiles once (a 700² window of a
    deflate-tiled view: 9.7 ms opened anew, 0.7 ms kept open). Each
    thread has its own datasets (rasterio's are not thread-safe); a file
    replaced since (another modification time, size or inode) is opened
    again.
    """
    import rasterio

    st = os.stat(path)
    key = (st.st_mtime_ns, st.st_size, st.st_ino)
    cache = getattr(_OPEN, "datasets", None)
    if cache is None:
        cache = _OPEN.datasets = {}
    held = cache.get(path)
    if held is not None and held[0] == key:
        return held[1]
    if held is not None:
        held[1].close()
    ds = rasterio.open(path)
    cache[path] = (key, ds)
    return ds


def read_window(view: View, window: tuple[int, int, int, int]) -> np.ndarray:
    """Pixels of ``view`` in ``(row0, row1, col0, col1)`` as float32, NaN nodata."""
    from rasterio.windows import Window

    r0, r1, c0, c1 = window
    arr = _dataset(view.path).read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
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

    Tie points are matched on overviews (at most :data:`TIEPOINT_OVERVIEW_PX` a side), triangulated
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
    from concurrent.futures import ThreadPoolExecutor

    from tiledsm.geometry.footprint import overlap_lonlat_bounds
    from tiledsm.match.tiepoints import height_range_from_tiepoints, match_tiepoints, relative_correction

    report: dict = {}
    factor = max(1, int(math.ceil(max(max(v.shape) for v in views) / TIEPOINT_OVERVIEW_PX)))
    ref = views[0]
    # GDAL's decimated reads release the GIL: all views' overviews at once
    with ThreadPoolExecutor(max_workers=min(len(views), 4)) as pool:
        overviews = list(pool.map(lambda v: _overview(v, factor), views))
    ref_img = overviews[0]
    corrected = [ref]
    ranges = []
    for i, other in enumerate(views[1:], start=1):
        # RPCs of images that share no ground (another hemisphere, another scene) match nothing real; say so
        # before tie points are triangulated into nonsense or localisation fails to converge
        rpcs = (ref.rpc, other.rpc)
        overlap_lonlat_bounds(ref.rpc, ref.shape, other.rpc, other.shape,
                              (min(r.height_off - abs(r.height_scale) for r in rpcs),
                               max(r.height_off + abs(r.height_scale) for r in rpcs)))
        p1, p2 = match_tiepoints(ref_img, overviews[i])
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
    res = params.resolution or mean_gsd(views, sum(h_range) / 2)
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    # the densified lon/lat box: its edges are curved in a projected CRS
    t = np.linspace(0.0, 1.0, 17)
    lons = np.concatenate([lon0 + t * (lon1 - lon0), np.full(17, lon1), lon0 + t * (lon1 - lon0), np.full(17, lon0)])
    lats = np.concatenate([np.full(17, lat0), lat0 + t * (lat1 - lat0), np.full(17, lat1), lat0 + t * (lat1 - lat0)])
    xs, ys = tr.transform(lons, lats)
    bounds = (min(xs), min(ys), max(xs), max(ys))
    return GroundGrid.from_bounds(crs, bounds, res, chunk=params.chunk)


def mean_gsd(views: Sequence[View], h: float) -> float:
    """The views' mean ground sample distance, metres (rounded to the
    millimetre): the ground length of one pixel step along rows and along
    columns at each view's centre, at ellipsoidal height ``h``."""
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    gsds = []
    for v in views:
        r, c = v.shape[0] / 2, v.shape[1] / 2
        lon, lat = v.rpc.localize(np.array([r, r + 1, r]), np.array([c, c, c + 1]), h)
        gsds.append(geod.inv(lon[0], lat[0], lon[1], lat[1])[2])
        gsds.append(geod.inv(lon[0], lat[0], lon[2], lat[2])[2])
    return float(np.round(np.mean(gsds), 3))


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
