"""A reference DEM (e.g. SRTM) as a height function of lon/lat.

The part of the DEM covering a lon/lat box is read once (a window, never
the whole file) and sampled bilinearly in the DEM's own CRS. Heights are
returned above the WGS84 ellipsoid: with a geoid grid, the DEM is taken as
heights above that geoid (SRTM: EGM96) and ``N`` is added.

Conventions: lon/lat WGS84 degrees; DEM values are node values at GDAL pixel
centres; nodata and points outside the DEM give NaN.

A DEM cell is an area average (SRTM: about 30 m), a tie point a point: on
slopes, and next to buildings that raise the average of the cells around
them, the two differ by about ``cell size x |gradient|``.
:meth:`ReferenceDEM.slope_sigma` gives that term per point, so the
adjustment can weight flat ground above relief
(:attr:`tiledsm.orient.adjust.Block.dem_slope_sigma_m`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from tiledsm.errors import InputFileError

__all__ = ["ReferenceDEM", "bilinear"]


@lru_cache(maxsize=8)
def _to_crs(crs: str):
    from pyproj import Transformer

    return Transformer.from_crs("EPSG:4326", crs, always_xy=True)


def bilinear(grid: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``grid`` at fractional array indices
    (node ``[i, j]`` at ``(i, j)``); NaN outside the grid or next to a NaN
    node."""
    from scipy.ndimage import map_coordinates

    rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    out = map_coordinates(grid, [rows.ravel(), cols.ravel()], order=1, mode="constant", cval=np.nan,
                          prefilter=False)
    inside = (rows.ravel() >= 0) & (rows.ravel() <= grid.shape[0] - 1) & (cols.ravel() >= 0) & (cols.ravel() <= grid.shape[1] - 1)
    out[~inside] = np.nan
    return out.reshape(rows.shape)


@dataclass(frozen=True)
class ReferenceDEM:
    """Heights of a DEM window, callable as ``dem(lon, lat) -> h`` (metres,
    WGS84 ellipsoidal).

    Attributes
    ----------
    grid : numpy.ndarray
        DEM values of the window (float64, NaN = nodata), geoid added
        when a geoid was given.
    transform : affine.Affine
        GDAL transform of ``grid``.
    crs : str
        The DEM's CRS (WKT or EPSG string).
    source : str
    """

    grid: np.ndarray
    transform: object
    crs: str
    source: str

    @classmethod
    def open(cls, path: str | Path, lon_range: tuple[float, float], lat_range: tuple[float, float],
             geoid: str | Path | None = None, margin_cells: int = 3) -> "ReferenceDEM":
        """Read the window of ``path`` covering a lon/lat box.

        Raises
        ------
        InputFileError
            Missing/unreadable DEM, no CRS, or no overlap with the box.
        """
        import rasterio
        from pyproj import Transformer
        from rasterio.windows import Window, from_bounds

        from tiledsm.io.geoid import geoid_height

        path = Path(path)
        if not path.is_file():
            raise InputFileError(f"{path}: reference DEM not found")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ds = rasterio.open(path)
        except rasterio.errors.RasterioIOError as exc:
            raise InputFileError(f"{path}: not a readable DEM ({exc})") from exc
        with ds:
            if ds.crs is None:
                raise InputFileError(f"{path}: reference DEM has no CRS")
            tr = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True)
            lo = np.linspace(*lon_range, 9)
            la = np.linspace(*lat_range, 9)
            x, y = tr.transform(*np.meshgrid(lo, la))
            win = from_bounds(x.min(), y.min(), x.max(), y.max(), ds.transform)
            r0 = max(int(np.floor(win.row_off)) - margin_cells, 0)
            c0 = max(int(np.floor(win.col_off)) - margin_cells, 0)
            r1 = min(int(np.ceil(win.row_off + win.height)) + margin_cells, ds.height)
            c1 = min(int(np.ceil(win.col_off + win.width)) + margin_cells, ds.width)
            if r1 <= r0 or c1 <= c0:
                raise InputFileError(f"{path}: reference DEM does not cover lon {lon_range}, lat {lat_range}")
            w = Window(c0, r0, c1 - c0, r1 - r0)
            grid = ds.read(1, window=w, masked=True).astype(np.float64).filled(np.nan)
            transform = ds.window_transform(w)
            crs = ds.crs.to_string()
        if geoid is not None:
            ii, jj = np.mgrid[0: grid.shape[0], 0: grid.shape[1]]
            gx, gy = transform * (jj + 0.5, ii + 0.5)
            glon, glat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(gx, gy)
            grid = grid + geoid_height(glon, glat, geoid)
        grid.setflags(write=False)
        return cls(grid, transform, crs, f"{path}" + (f" + geoid {Path(geoid).name}" if geoid else ""))

    @classmethod
    def for_cameras(cls, path: str | Path, rpcs, shapes, geoid: str | Path | None = None) -> "ReferenceDEM":
        """:meth:`open` over the ground box of images: every image's footprint
        (``rpcs[i]`` over ``shapes[i]`` = (rows, cols)) across its RPC's
        height range."""
        lon_r, lat_r = [], []
        for rpc, (nr, nc) in zip(rpcs, shapes):
            hs = abs(rpc.height_scale)
            (lo, hi), (la, lb) = rpc.ground_box((0.0, float(nr), 0.0, float(nc)),
                                                (rpc.height_off - hs, rpc.height_off + hs))
            lon_r += [lo, hi]
            lat_r += [la, lb]
        return cls.open(path, (min(lon_r), max(lon_r)), (min(lat_r), max(lat_r)), geoid=geoid)

    def _index(self, lon, lat) -> tuple[np.ndarray, np.ndarray]:
        x, y = _to_crs(self.crs).transform(np.asarray(lon, float), np.asarray(lat, float))
        col, row = ~self.transform * (np.asarray(x), np.asarray(y))
        return np.asarray(row) - 0.5, np.asarray(col) - 0.5

    def __call__(self, lon, lat) -> np.ndarray:
        return bilinear(self.grid, *self._index(lon, lat))

    def cell_m(self) -> tuple[float, float]:
        """Cell size ``(along y, along x)`` in metres (a geographic DEM's
        degrees converted at the window's central latitude)."""
        from pyproj import CRS

        dy, dx = abs(self.transform.e), abs(self.transform.a)
        if CRS.from_user_input(self.crs).is_geographic:
            lat = self.transform.f + self.transform.e * 0.5 * self.grid.shape[0]
            m = 6378137.0 * np.pi / 180.0
            return dy * m, dx * m * np.cos(np.radians(lat))
        return dy, dx

    def slope_sigma(self, lon, lat) -> np.ndarray:
        """Representativeness error of the DEM at points, metres:
        ``cell size x |gradient|`` (gradient by central differences over the
        grid, sampled bilinearly); NaN where the DEM is."""
        cy, cx = self.cell_m()
        gy, gx = np.gradient(self.grid, cy, cx)
        r, c = self._index(lon, lat)
        return np.hypot(bilinear(gy, r, c) * cy, bilinear(gx, r, c) * cx)
