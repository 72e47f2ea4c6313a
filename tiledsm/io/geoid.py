"""Geoid undulation from a grid file, and geoid <-> ellipsoid heights.

``N(lon, lat)`` is bilinearly interpolated in a global or regional
geographic grid read by GDAL (``.gtx`` such as EGM96 ``egm96_15.gtx``, or
any single-band EPSG:4326 raster). Grid values are node values at the
*centres* of GDAL's pixels. Longitudes wrap (a grid covering 360 degrees
interpolates across the antimeridian); latitudes are clamped to the grid.

Conventions: lon/lat WGS84 degrees; heights in metres;
``h_ellipsoid = H_geoid + N``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from tiledsm.errors import InputFileError

__all__ = ["load_geoid", "geoid_height", "geoid_to_ellipsoid", "ellipsoid_to_geoid"]


@lru_cache(maxsize=4)
def load_geoid(path: str) -> tuple[np.ndarray, float, float, float, float, bool]:
    """(grid, lon0, lat0, dlon, dlat, wraps): node [i, j] at
    (lon0 + j*dlon, lat0 - i*dlat)."""
    import rasterio
    from rasterio.errors import RasterioIOError

    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: geoid grid not found")
    try:
        with rasterio.open(p) as ds:
            grid = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
            t = ds.transform
    except RasterioIOError as exc:
        raise InputFileError(f"{p}: not a readable geoid grid ({exc})") from exc
    if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
        raise InputFileError(f"{p}: geoid grid must be north-up lon/lat (geotransform {tuple(t)[:6]})")
    dlon, dlat = t.a, -t.e
    lon0, lat0 = t.c + dlon / 2, t.f - dlat / 2
    wraps = abs(grid.shape[1] * dlon - 360.0) < 1e-6 * dlon
    grid.setflags(write=False)
    return grid, lon0, lat0, dlon, dlat, wraps


def geoid_height(lon, lat, grid_path: str | Path) -> np.ndarray:
    """Geoid undulation ``N`` (metres above the WGS84 ellipsoid).

    Parameters
    ----------
    lon, lat : array_like
        WGS84 degrees; broadcast together.
    grid_path : str or Path
        Geoid grid file (e.g. ``egm96_15.gtx``).

    Returns
    -------
    numpy.ndarray
        ``N`` by bilinear interpolation; NaN outside a regional grid or on
        its nodata.

    Raises
    ------
    InputFileError
        The grid file is missing or unreadable.
    """
    grid, lon0, lat0, dlon, dlat, wraps = load_geoid(str(Path(grid_path).resolve()))
    lon, lat = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
    ny, nx = grid.shape
    x = (lon - lon0) / dlon
    y = (lat0 - lat) / dlat
    outside_lat = (y < -1e-9) | (y > ny - 1 + 1e-9)
    y = np.clip(y, 0, ny - 1)
    if wraps:
        x = np.mod(x, nx)
        j0 = np.floor(x).astype(np.int64)
        j1 = (j0 + 1) % nx
    else:
        out = (x < 0) | (x > nx - 1)
        x = np.clip(x, 0, nx - 1)
        j0 = np.minimum(np.floor(x).astype(np.int64), nx - 2)
        j1 = j0 + 1
    i0 = np.minimum(np.floor(y).astype(np.int64), ny - 2)
    fx, fy = x - j0, y - i0
    n = ((1 - fy) * ((1 - fx) * grid[i0, j0] + fx * grid[i0, j1])
         + fy * ((1 - fx) * grid[i0 + 1, j0] + fx * grid[i0 + 1, j1]))
    if not wraps:
        n = np.where(out, np.nan, n)
    return np.where(outside_lat, np.nan, n)


def geoid_to_ellipsoid(lon, lat, h, grid_path: str | Path) -> np.ndarray:
    """Heights above the geoid (e.g. SRTM, metres) to heights above the WGS84
    ellipsoid: ``h + N(lon, lat)``."""
    return np.asarray(h, float) + geoid_height(lon, lat, grid_path)


def ellipsoid_to_geoid(lon, lat, h, grid_path: str | Path) -> np.ndarray:
    """Heights above the WGS84 ellipsoid to heights above the geoid:
    ``h - N(lon, lat)``."""
    return np.asarray(h, float) - geoid_height(lon, lat, grid_path)
