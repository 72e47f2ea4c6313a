"""One grid for two orthoimages: the grid the displacement is measured on,
and each ortho read onto it (``tiledsm displace``).

Two orthos made by different pipelines rarely share a grid: another CRS
(UTM zone), another cell size, another origin. Correlating them as they
are would measure the grid offset as ground motion, so both are brought
onto one grid first:

- by default **PRE's own pixel lattice** (its CRS, cell size and origin),
  cropped to the part POST covers: PRE is read as it is (no resampling),
  POST is warped onto it;
- or the lattice of a raster the user gives (``like``), or PRE's CRS and
  origin with another cell size (``resolution``): both are warped.

Warping is GDAL's (:func:`rasterio.warp.reproject`, bicubic: Keys' cubic
convolution, ``a = -0.5``) one chunk at a time, each chunk reading only
the source window it needs; pixels outside a source (or its nodata) are
NaN. The grid is north-up and in metres (a geographic CRS is refused:
displacements are metres east/north).

Conventions: transforms are GDAL's (pixel ``[i, j]`` covers
``transform * (j, i)`` .. ``transform * (j + 1, i + 1)``); shapes
``(rows, columns)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tiledsm.errors import GridError, InputFileError, NoOverlapError

__all__ = ["OrthoGrid", "ortho_header", "displacement_grid", "read_on_grid"]

#: resampling of an ortho warped onto the grid (GDAL's cubic: Keys, a = -0.5)
RESAMPLING = "cubic"


@dataclass(frozen=True)
class OrthoGrid:
    """A north-up grid: CRS (WKT or EPSG string), GDAL transform, shape,
    and where it comes from (for the plan)."""

    crs: str
    transform: tuple[float, float, float, float, float, float]
    shape: tuple[int, int]
    source: str

    @property
    def resolution(self) -> float:
        return abs(self.transform[0])

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        a, _, c, _, e, f = self.transform
        return (c, f + self.shape[0] * e, c + self.shape[1] * a, f)

    def affine(self):
        from affine import Affine

        return Affine(*self.transform)

    def text(self) -> str:
        from rasterio.crs import CRS

        crs = CRS.from_user_input(self.crs)
        name = crs.to_string() if crs.to_epsg() else crs.to_wkt()[:60]
        return (f"{self.shape[0]} x {self.shape[1]} cells of {self.resolution:g} m, {name}, origin (top-left corner) "
                f"({self.transform[2]:.3f}, {self.transform[5]:.3f}); {self.source}")


def ortho_header(path: str, name: str) -> dict:
    """CRS, transform, shape and bounds of an orthoimage (a GDAL raster or a
    tiledsm ``.zarr`` store); refuses one that is not georeferenced, not
    north-up, or in a geographic CRS, naming ``name``."""
    import warnings

    import rasterio

    from tiledsm.plan.core import store_raster

    if Path(path).is_dir():
        a = store_raster(path, name)
        crs, t, shape = a.rio.crs, a.rio.transform(), a.rio.shape
    else:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                with rasterio.open(path) as src:
                    crs, t, shape = src.crs, src.transform, (src.height, src.width)
        except rasterio.errors.RasterioIOError as exc:
            raise InputFileError(f"{path}: {name}: not a readable raster ({exc})") from None
    if crs is None or t.is_identity:
        raise GridError(f"{path}: {name}: not georeferenced (no CRS or geotransform): give an orthoimage "
                        "(a raster with a projected CRS and a geotransform)")
    if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
        raise GridError(f"{path}: {name}: its grid is rotated or not north-up ({tuple(t)[:6]}); warp it north-up first")
    if crs.is_geographic:
        raise GridError(f"{path}: {name}: its CRS ({crs.to_string()}) is in degrees; give --like a raster in a "
                        "projected CRS (metres), e.g. UTM")
    x0, y0 = t.c, t.f
    return {"crs": crs.to_wkt(), "crs_name": crs.to_string(), "transform": tuple(t)[:6], "shape": tuple(shape),
            "bounds": (x0, y0 + shape[0] * t.e, x0 + shape[1] * t.a, y0), "res": (t.a, -t.e)}


def _bounds_in(head: dict, crs: str) -> tuple[float, float, float, float]:
    from rasterio.crs import CRS
    from rasterio.warp import transform_bounds

    if CRS.from_user_input(head["crs"]) == CRS.from_user_input(crs):
        return head["bounds"]
    return transform_bounds(head["crs"], crs, *head["bounds"], densify_pts=21)


def displacement_grid(pre: dict, post: dict, *, like: dict | None = None, resolution: float | None = None,
                      names: tuple[str, str] = ("PRE", "POST"), min_side: int = 0) -> OrthoGrid:
    """The grid both orthos are read onto (module notes), cropped to what
    PRE and POST (and ``like``) cover together, on the base lattice.

    Parameters
    ----------
    pre, post, like : dict
        :func:`ortho_header` of each.
    resolution : float, optional
        Cell size, metres (PRE's CRS and origin).
    min_side : int
        Fewest cells per side the overlap must have (one correlation window).

    Raises
    ------
    NoOverlapError
        The footprints do not overlap by ``min_side`` cells.
    """
    base = like if like is not None else pre
    a, _, x0, _, e, y0 = base["transform"]
    source = "the lattice of --like" if like is not None else "PRE's own pixel lattice"
    if resolution is not None and like is None:
        a, e = float(resolution), -float(resolution)
        source = f"PRE's CRS and origin, cells of {resolution:g} m"
    crs = base["crs"]
    lattice = (a, 0.0, x0, 0.0, e, y0)
    how = ["read as is" if same_lattice(crs, lattice, h["crs"], h["transform"]) else "warped onto it (bicubic)"
           for h in (pre, post)]
    source += (f"; {names[0]} and {names[1]} {how[0]}" if how[0] == how[1]
               else f"; {names[0]} {how[0]}, {names[1]} {how[1]}")
    boxes = [_bounds_in(h, crs) for h in (pre, post, *([like] if like is not None else []))]
    left, bottom = max(b[0] for b in boxes), max(b[1] for b in boxes)
    right, top = min(b[2] for b in boxes), min(b[3] for b in boxes)
    # the overlap on the lattice: whole cells inside it
    j0, j1 = math.ceil((left - x0) / a - 1e-6), math.floor((right - x0) / a + 1e-6)
    i0, i1 = math.ceil((y0 - top) / -e - 1e-6), math.floor((y0 - bottom) / -e + 1e-6)
    if j1 - j0 < max(min_side, 1) or i1 - i0 < max(min_side, 1):
        what = f"{max(0, i1 - i0)} x {max(0, j1 - j0)} cells" if (j1 > j0 and i1 > i0) else "nothing"
        raise NoOverlapError(f"{names[1]} and {names[0]} have {what} of ground in common"
                             + (f" (one correlation window needs {min_side} x {min_side})" if min_side else "")
                             + f": {names[0]} covers {_fmt(boxes[0])}, {names[1]} {_fmt(boxes[1])} in the grid's CRS")
    t = (a, 0.0, x0 + j0 * a, 0.0, e, y0 + i0 * e)
    return OrthoGrid(crs, t, (i1 - i0, j1 - j0), source)


def same_lattice(crs_a, t_a, crs_b, t_b) -> bool:
    """Whether grid b's pixels are grid a's (same CRS and cell size, an
    origin a whole number of cells away): reading b onto a needs no
    resampling."""
    from rasterio.crs import CRS

    if CRS.from_user_input(crs_a) != CRS.from_user_input(crs_b):
        return False
    col = (t_b[2] - t_a[2]) / t_a[0]
    row = (t_b[5] - t_a[5]) / t_a[4]
    return (math.isclose(t_a[0], t_b[0], rel_tol=1e-9) and math.isclose(t_a[4], t_b[4], rel_tol=1e-9)
            and abs(col - round(col)) < 1e-6 and abs(row - round(row)) < 1e-6)


def _fmt(b) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in b) + ")"


def _read_block(path: str, grid_crs: str, transform: tuple, shape: tuple[int, int]) -> np.ndarray:
    """Pixels of the raster ``path`` on the block grid ``(transform,
    shape)``: a plain window read when the block lies on the raster's own
    lattice, else GDAL's bicubic warp; NaN outside the raster and at its
    nodata."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.warp import reproject
    from rasterio.windows import Window

    out = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as src:
        st = src.transform
        if same_lattice(src.crs, tuple(st)[:6], grid_crs, transform):
            r0, c0 = int(round((transform[5] - st.f) / st.e)), int(round((transform[2] - st.c) / st.a))
            a0, a1 = max(r0, 0), min(r0 + shape[0], src.height)
            b0, b1 = max(c0, 0), min(c0 + shape[1], src.width)
            if a1 > a0 and b1 > b0:
                v = src.read(1, window=Window(b0, a0, b1 - b0, a1 - a0), masked=True)
                out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = v.astype(np.float32).filled(np.nan)
            return out
        from affine import Affine

        reproject(rasterio.band(src, 1), out, src_nodata=src.nodata, dst_transform=Affine(*transform),
                  dst_crs=grid_crs, dst_nodata=np.nan, resampling=Resampling[RESAMPLING], init_dest_nodata=True)
    return out


def _zarr_on_grid(path: str, grid: OrthoGrid):
    """A tiledsm ortho store on the grid: cropped when it shares the
    lattice, else warped in memory (rioxarray, bicubic)."""
    import xarray as xr
    from rasterio.enums import Resampling

    from tiledsm.io import open_raster_product

    a = open_raster_product(path).astype(np.float32)
    t_a = tuple(a.rio.transform())[:6]
    if same_lattice(a.rio.crs, t_a, grid.crs, grid.transform):
        r0 = int(round((grid.transform[5] - t_a[5]) / t_a[4]))
        c0 = int(round((grid.transform[2] - t_a[2]) / t_a[0]))
        out = np.full(grid.shape, np.nan, np.float32)
        a0, a1 = max(r0, 0), min(r0 + grid.shape[0], a.shape[0])
        b0, b1 = max(c0, 0), min(c0 + grid.shape[1], a.shape[1])
        if a1 > a0 and b1 > b0:
            out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = np.asarray(a.data[a0:a1, b0:b1])
        return out
    like = xr.DataArray(np.zeros(grid.shape, np.float32), dims=("y", "x")).rio.write_crs(grid.crs)
    like = like.rio.write_transform(grid.affine())
    t = grid.affine()
    like = like.assign_coords(x=t.c + (np.arange(grid.shape[1]) + 0.5) * t.a,
                              y=t.f + (np.arange(grid.shape[0]) + 0.5) * t.e)
    return a.rio.reproject_match(like, resampling=Resampling[RESAMPLING], nodata=np.nan).data


def read_on_grid(path: str, grid: OrthoGrid, chunk: int = 1024):
    """The ortho ``path`` on ``grid`` as a lazy float32 dask array (NaN =
    no data), one chunk per task (module notes)."""
    import dask.array as da
    from dask.base import tokenize

    if Path(path).is_dir():
        arr = _zarr_on_grid(path, grid)
        return da.asarray(arr).rechunk(chunk).astype(np.float32)
    a, _, x0, _, e, y0 = grid.transform
    chunks = da.core.normalize_chunks(chunk, grid.shape)

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"]
        t = (a, 0.0, x0 + c0 * a, 0.0, e, y0 + r0 * e)
        return _read_block(path, grid.crs, t, (r1 - r0, c1 - c0))

    return da.map_blocks(block, chunks=chunks, dtype=np.float32, meta=np.empty((0, 0), np.float32),
                         name=f"on-grid-{tokenize(path, grid, chunk)}")
