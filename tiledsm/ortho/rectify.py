"""Tiled orthorectification: the orthoimage of one image (RPC or frame
camera) on a DSM's ground grid or a finer one, with occlusion.

For every output cell (one dask task per chunk of the ortho grid):

1. its height is the DSM's, interpolated bilinearly when the ortho grid is
   ``factor`` times finer than the DSM's (cell centres; the DSM's border
   cells are replicated half a cell outwards);
2. the cell's surface point is projected into the image by the camera and
   the image is interpolated there with a kernel of
   :data:`tiledsm.ortho.kernels.KERNELS` (NN, BL, CR, CS), from the image
   window the chunk's points need (plus the kernel support), read per task;
3. with ``occlusion``, the line of sight from the surface point towards the
   sensor is marched over the DSM (steps of ``step`` DSM cells, bilinear
   heights): a cell whose ray passes more than ``occlusion_tolerance``
   metres below the DSM is hidden from the view and set to NaN (a z-buffer
   by ray casting). The ray direction is the camera's height parallax
   (:func:`tiledsm.geometry.camera.height_parallax`), so any camera works.

The parameters are :class:`tiledsm.ortho.recipe.OrthoSpec` (the recipe's
``ortho:`` section); the refinement ``factor`` is an argument of its own,
derived from the ortho grid's resolution.

Tiling: the DSM is read with a halo of ``ceil((hmax - hmin) |v|max / res) + 2``
cells (``hmin``, ``hmax`` the DSM's height range, ``|v|max`` the largest
tangent of the off-nadir angle over the grid): a ray leaves the halo only
above every DSM height, so each task sees everything that can hide its
cells, and the result is independent of the chunking (tested: chunks 64 and
512 give identical orthos).

Conventions
-----------
- Ortho cells follow :class:`~tiledsm.geometry.grid.GroundGrid` (corner
  ``x0, y0``, cell ``[i, j]`` centred at ``x0 + (j+.5) res``,
  ``y0 - (i+.5) res``); the ortho grid of factor ``f`` has the DSM grid's
  outer corner and ``res / f`` cells.
- Image pixels are GDAL's (camera protocol); heights are whatever the
  camera expects (WGS84 ellipsoidal for RPCs): the DSM must use the same
  datum.
- Output: float32 digital numbers, NaN where the DSM has no height, the
  point falls outside the image, or the cell is hidden.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import dask.array as da
import numba
import numpy as np
import xarray as xr

from tiledsm.errors import GridError, InvalidOptionError, NoOverlapError
from tiledsm.geometry.camera import Camera, height_parallax
from tiledsm.geometry.footprint import to_lonlat
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.ortho.kernels import get_kernel, sample
from tiledsm.ortho.recipe import OrthoSpec

__all__ = ["ImageSource", "ortho_grid", "orthorectify", "ortho_halo", "check_sees"]


@dataclass(frozen=True, eq=False)
class ImageSource:
    """An image and its camera; pixels read window by window.

    Either ``path`` (any raster GDAL reads, band ``band``) or ``array``
    (in memory, ``(rows, cols)``).
    """

    camera: Camera
    shape: tuple[int, int]
    path: str | None = None
    array: np.ndarray | None = field(default=None, repr=False)
    band: int = 1
    name: str = ""

    @classmethod
    def from_array(cls, array: np.ndarray, camera: Camera, name: str = "") -> "ImageSource":
        arr = np.asarray(array, np.float32)
        return cls(camera, arr.shape, array=arr, name=name or getattr(camera, "source", "") or "array")

    @classmethod
    def from_file(cls, path: str | Path, camera: Camera | None = None, band: int = 1) -> "ImageSource":
        """An image file with ``camera`` (default: its RPC, from tags or a
        sidecar, :func:`tiledsm.io.cameras.find_camera`)."""
        import rasterio

        from tiledsm.errors import InputFileError

        p = Path(path)
        if not p.is_file():
            raise InputFileError(f"{p}: no such image")
        if camera is None:
            from tiledsm.io.cameras import find_camera

            camera, _ = find_camera(p, None)
        try:
            with sensor_geometry(), rasterio.open(p) as ds:
                shape = (ds.height, ds.width)
        except rasterio.errors.RasterioIOError as exc:
            raise InputFileError(f"{p}: not a readable raster ({exc})") from exc
        return cls(camera, shape, path=str(p), band=band, name=str(p))

    def read(self, window: tuple[int, int, int, int]) -> np.ndarray:
        """Pixels ``[row0:row1, col0:col1]`` as float32, NaN nodata."""
        r0, r1, c0, c1 = window
        if self.array is not None:
            return self.array[r0:r1, c0:c1]
        import rasterio
        from rasterio.windows import Window

        with sensor_geometry(), rasterio.open(self.path) as ds:
            arr = ds.read(self.band, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True)
        return arr.astype(np.float32).filled(np.nan)


def sensor_geometry():
    """Silence rasterio's warning for images without georeference (by design)."""
    import warnings
    from contextlib import contextmanager

    from rasterio.errors import NotGeoreferencedWarning

    @contextmanager
    def ctx():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            yield

    return ctx()


def ortho_grid(dsm_grid: GroundGrid, factor: int, chunk: int | None = None) -> GroundGrid:
    """The ortho grid ``factor`` times finer than ``dsm_grid`` (same outer
    corner and CRS); ``chunk`` (default ``dsm_grid.chunk * factor``) must
    be a multiple of ``factor``."""
    f = int(factor)
    chunk = int(chunk or dsm_grid.chunk * f)
    if chunk % f:
        raise InvalidOptionError(f"chunk: must be a multiple of the resolution factor {f}, got {chunk}")
    return GroundGrid(dsm_grid.crs, dsm_grid.x0, dsm_grid.y0, dsm_grid.resolution / f,
                      dsm_grid.width * f, dsm_grid.height * f, chunk)


def _lattice(grid: GroundGrid, n: int = 17) -> tuple[np.ndarray, np.ndarray]:
    """``n x n`` points spanning the grid's cell centres (edges included)."""
    xs = np.linspace(grid.x[0], grid.x[-1], n)
    ys = np.linspace(grid.y[0], grid.y[-1], n)
    return np.meshgrid(xs, ys)


def check_sees(source: ImageSource, grid: GroundGrid, h_range: tuple[float, float], dsm_name: str = "") -> float:
    """Share of a 17 x 17 lattice of the grid (at the mid height) that
    projects inside the image; ``dsm_name`` names the DSM in the error.

    Raises
    ------
    NoOverlapError
        The camera sees none of it.
    """
    X, Y = _lattice(grid)
    lon, lat = to_lonlat(grid.crs, X, Y)
    r, c = source.camera.project(lon, lat, 0.5 * (h_range[0] + h_range[1]))
    inside = (r >= 0) & (r <= source.shape[0]) & (c >= 0) & (c <= source.shape[1])
    if not inside.any():
        raise NoOverlapError(
            f"{source.name or 'image'}: its camera does not see the ground of the DSM{dsm_name} "
            f"(bounds {tuple(round(b, 2) for b in grid.bounds)} in {grid.crs}, heights "
            f"{h_range[0]:.1f}..{h_range[1]:.1f} m)")
    return float(inside.mean())


def ortho_halo(camera: Camera, dsm_grid: GroundGrid, h_range: tuple[float, float]) -> tuple[int, float]:
    """DSM halo (cells) for occlusion and the largest ``|v|`` (tangent of
    the off-nadir angle) over the grid, measured on a 17 x 17 lattice at
    both ends of ``h_range`` (+10 %)."""
    X, Y = _lattice(dsm_grid)
    vmax = 0.0
    for h in h_range:
        vx, vy = height_parallax(camera, dsm_grid.crs, X, Y, np.full(X.shape, float(h)))
        v = np.hypot(vx, vy)
        if np.isfinite(v).any():
            vmax = max(vmax, float(np.nanmax(v)))
    vmax *= 1.1
    halo = int(math.ceil((h_range[1] - h_range[0]) * vmax / dsm_grid.resolution)) + 2
    return halo, vmax


@numba.njit(nogil=True, cache=True, inline="always")
def _bilinear_nan(img, y, x):
    """Bilinear value at array-index coordinates; NaN outside or on NaN."""
    ny, nx = img.shape
    if not (y >= 0.0 and x >= 0.0 and y <= ny - 1 and x <= nx - 1):
        return np.nan
    i = min(int(math.floor(y)), ny - 2) if ny > 1 else 0
    j = min(int(math.floor(x)), nx - 2) if nx > 1 else 0
    ty = y - i
    tx = x - j
    i1 = min(i + 1, ny - 1)
    j1 = min(j + 1, nx - 1)
    top = img[i, j] * (1.0 - tx) + img[i, j1] * tx
    bot = img[i1, j] * (1.0 - tx) + img[i1, j1] * tx
    return top * (1.0 - ty) + bot * ty


@numba.njit(nogil=True, cache=True)
def hidden(dsm, py, px, z, vy, vx, res, step, tol, zmax, out):
    """Ray casting over a DSM block.

    For each point ``k`` at array-index position ``(py, px)`` of ``dsm``
    (cells of ``res`` metres, rows southward) and height ``z``, march the
    line of sight ``(px + vx t / res, py - vy t / res, z + t)`` upwards in
    horizontal steps of ``step`` cells until it is above ``zmax`` or leaves
    the block; ``out[k] = True`` when the DSM rises more than ``tol``
    metres above it somewhere.
    """
    for k in range(py.size):
        out[k] = False
        if not (np.isfinite(z[k]) and np.isfinite(vx[k]) and np.isfinite(vy[k])):
            continue
        g = math.sqrt(vx[k] * vx[k] + vy[k] * vy[k]) / res  # cells per metre of height
        if g < 1e-9:
            continue
        dt = step / g
        t = dt
        while z[k] + t <= zmax:
            y = py[k] - vy[k] * t / res
            x = px[k] + vx[k] * t / res
            hz = _bilinear_nan(dsm, y, x)
            if hz != hz:
                if not (y >= 0.0 and x >= 0.0 and y <= dsm.shape[0] - 1 and x <= dsm.shape[1] - 1):
                    break
            elif hz > z[k] + t + tol:
                out[k] = True
                break
            t += dt


def _fine_heights(block: np.ndarray, f: int, off: tuple[int, int], core: tuple[int, int],
                  dsm_shape: tuple[int, int], halo: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heights of the fine cells of a core (DSM cells ``off`` .. ``off + core``),
    and their DSM array-index positions inside ``block`` (the core plus
    ``halo = (rows, cols)`` cells). Fine cell ``i`` is centred at DSM index ``(i + .5) / f - .5``,
    clamped to the DSM (border replicated)."""
    R0, C0 = off
    nr, nc = core
    gy = R0 + (np.arange(nr * f) + 0.5) / f - 0.5
    gx = C0 + (np.arange(nc * f) + 0.5) / f - 0.5
    hy, hx = halo
    gy = np.clip(gy, 0, dsm_shape[0] - 1) - R0 + hy
    gx = np.clip(gx, 0, dsm_shape[1] - 1) - C0 + hx
    if f == 1:
        z = block[hy:hy + nr, hx:hx + nc].astype(np.float64)
    else:
        z = sample(block, gy[:, None] + 0.5, gx[None, :] + 0.5, "bl").astype(np.float64)
    PY, PX = np.meshgrid(gy, gx, indexing="ij")
    return z, PY, PX


def _ortho_block(block, *, source: ImageSource, grid: GroundGrid, dsm_shape, core_chunks, halo: tuple[int, int],
                 params: OrthoSpec, factor: int, zmax: float, block_id=None) -> np.ndarray:
    """One chunk of the ortho, ``factor`` times finer than the DSM: ``block``
    is the DSM core ``block_id`` plus ``halo = (rows, cols)`` cells (NaN
    beyond the DSM)."""
    f = factor
    bi, bj = block_id
    R0, C0 = sum(core_chunks[0][:bi]), sum(core_chunks[1][:bj])
    nr, nc = core_chunks[0][bi], core_chunks[1][bj]
    dsm = np.asarray(block, np.float64)
    z, PY, PX = _fine_heights(dsm, f, (R0, C0), (nr, nc), dsm_shape, halo)
    res_f = grid.resolution
    xs = grid.x0 + (C0 * f + np.arange(nc * f) + 0.5) * res_f
    ys = grid.y0 - (R0 * f + np.arange(nr * f) + 0.5) * res_f
    X, Y = np.meshgrid(xs, ys)
    out = np.full(z.shape, np.nan, np.float32)
    ok = np.isfinite(z)
    if not ok.any():
        return out
    lon, lat = to_lonlat(grid.crs, X[ok], Y[ok])
    rows, cols = source.camera.project(lon, lat, z[ok])
    rows, cols = np.asarray(rows, float), np.asarray(cols, float)
    nrow, ncol = source.shape
    inside = (rows >= 0) & (rows <= nrow) & (cols >= 0) & (cols <= ncol)
    if not inside.any():
        return out
    kern = get_kernel(params.kernel)
    m = kern.radius + 1
    r0 = max(int(math.floor(rows[inside].min())) - m, 0)
    r1 = min(int(math.floor(rows[inside].max())) + m + 1, nrow)
    c0 = max(int(math.floor(cols[inside].min())) - m, 0)
    c1 = min(int(math.floor(cols[inside].max())) + m + 1, ncol)
    window = source.read((r0, r1, c0, c1))
    vals = sample(window, rows, cols, kern, origin=(r0, c0), shape=source.shape)
    if params.occlusion:
        res = grid.resolution * f
        tol = res if params.occlusion_tolerance is None else float(params.occlusion_tolerance)
        vx, vy = height_parallax(source.camera, grid.crs, X[ok], Y[ok], z[ok])
        hid = np.empty(vals.size, np.bool_)
        hidden(dsm, PY[ok].astype(np.float64), PX[ok].astype(np.float64), z[ok], np.asarray(vy, float),
               np.asarray(vx, float), float(res), float(params.step), float(tol), float(zmax), hid)
        vals[hid] = np.nan
    out[ok] = vals
    return out


def _as_height(dsm) -> xr.DataArray:
    if isinstance(dsm, xr.Dataset):
        if "height" not in dsm:
            raise GridError(f"DSM dataset has no 'height' variable (variables: {list(dsm.data_vars)})")
        dsm = dsm["height"]
    if dsm.ndim == 3 and dsm.sizes.get("band", 0) == 1:
        dsm = dsm.squeeze("band", drop=True)
    if dsm.dims != ("y", "x"):
        raise GridError(f"DSM: expected dims (y, x), got {dsm.dims}")
    return dsm


def orthorectify(
    source: ImageSource,
    dsm: xr.DataArray | xr.Dataset,
    params: OrthoSpec = OrthoSpec(),
    *,
    factor: int = 1,
    chunk: int | None = None,
    bounds: tuple[float, float, float, float] | None = None,
    crs: str | None = None,
    h_range: tuple[float, float] | None = None,
) -> xr.DataArray:
    """Lazy orthoimage of ``source`` on the DSM's grid refined ``factor`` times.

    Parameters
    ----------
    source : ImageSource
        The image and its camera.
    dsm : DataArray or Dataset
        Heights (the camera's datum), ``(y, x)`` on a north-up projected
        grid with rioxarray CRS/transform, NaN = no height; a Dataset's
        ``height`` variable.
    params : OrthoSpec
        Kernel, occlusion, its tolerance and ray-marching step.
    factor : int
        Ortho cells per DSM cell side (ortho resolution = DSM resolution
        / factor), >= 1.
    chunk : int, optional
        Ortho chunk side, cells (multiple of ``factor``; default the
        DSM's chunk times the factor).
    bounds : (left, bottom, right, top), optional
        Restrict the ortho to this box (DSM CRS; snapped outward to DSM
        cells); it must lie inside the DSM.
    crs : str, optional
        The CRS the caller expects; must be the DSM's.
    h_range : (hmin, hmax), optional
        Height range of the DSM (default: computed from it).

    Returns
    -------
    xarray.DataArray
        ``ortho`` float32 ``(y, x)``, dask-backed, CRS/transform written;
        attrs ``kernel``, ``factor``, ``camera_source``, ``halo_cells``,
        ``seen_share`` (of the region, seen by the camera: :func:`check_sees`).

    Raises
    ------
    InvalidOptionError
        ``factor`` is not an integer >= 1.
    GridError
        Mismatched CRS, ``bounds`` outside the DSM, no height in the region.
    NoOverlapError
        The camera does not see the region.
    """
    import rioxarray  # noqa: F401

    if int(factor) != factor or factor < 1:
        raise InvalidOptionError(f"factor: must be an integer >= 1, got {factor!r}")
    f = int(factor)
    height = _as_height(dsm)
    dgrid = grid_like(height, chunk=chunk // f if chunk else None)
    if crs is not None:
        from pyproj import CRS

        if CRS.from_user_input(crs) != CRS.from_user_input(dgrid.crs):
            raise GridError(f"crs: the ortho is asked in {crs} but the DSM is in {dgrid.crs}; reproject the DSM first")
    if bounds is not None:
        left, bottom, right, top = dgrid.bounds
        b = [float(v) for v in bounds]
        eps = 1e-6 * dgrid.resolution
        if b[0] < left - eps or b[1] < bottom - eps or b[2] > right + eps or b[3] > top + eps:
            raise GridError(f"bounds: {tuple(b)} is not covered by the DSM (bounds {dgrid.bounds} in {dgrid.crs})")
        c0 = int(math.floor((b[0] - dgrid.x0) / dgrid.resolution + 1e-9))
        c1 = int(math.ceil((b[2] - dgrid.x0) / dgrid.resolution - 1e-9))
        r0 = int(math.floor((dgrid.y0 - b[3]) / dgrid.resolution + 1e-9))
        r1 = int(math.ceil((dgrid.y0 - b[1]) / dgrid.resolution - 1e-9))
        height = height.isel(y=slice(r0, r1), x=slice(c0, c1))
        dgrid = dgrid.subgrid(r0, r1, c0, c1)
    data = height.data if isinstance(height.data, da.Array) else da.from_array(np.asarray(height.values))
    data = data.astype(np.float64).rechunk(dgrid.chunks)
    if h_range is None:
        lo, hi = da.compute(da.nanmin(data), da.nanmax(data))
        h_range = (float(lo), float(hi))
    if not all(np.isfinite(h_range)):
        raise GridError(f"DSM{_name(height)}: no height in the region (all NaN)")
    seen = check_sees(source, dgrid, h_range, _name(height))
    grid = ortho_grid(dgrid, f, chunk or dgrid.chunk * f)
    halo, vmax = ortho_halo(source.camera, dgrid, h_range) if params.occlusion else (0, 0.0)
    # per axis: a halo no deeper than the DSM (beyond it all is NaN) and
    # chunks at least as wide as the halo (dask's overlap needs it)
    from tiledsm.dsm import level_chunks

    depth = tuple(min(halo, n) for n in dgrid.shape)
    core = data.rechunk(tuple(level_chunks(n, max(dgrid.chunk, d), d) for n, d in zip(dgrid.shape, depth)))
    blocks = da.overlap.overlap(core, depth={0: depth[0], 1: depth[1]}, boundary=np.nan) if halo else core
    out = blocks.map_blocks(
        _ortho_block, source=source, grid=grid, dsm_shape=dgrid.shape, core_chunks=core.chunks, halo=depth,
        params=params, factor=f, zmax=float(h_range[1]), chunks=tuple(tuple(c * f for c in cs) for cs in core.chunks),
        dtype=np.float32, meta=np.empty((0, 0), np.float32), name="ortho",
    ).rechunk(grid.chunks)
    result = xr.DataArray(out, dims=("y", "x"), coords=grid.coords(), name="ortho")
    result = result.rio.write_crs(grid.crs).rio.write_transform(grid.transform)
    result.attrs.update(
        kernel=get_kernel(params.kernel).label, factor=f, camera_source=str(getattr(source.camera, "source", "")),
        image=source.name, occlusion=int(params.occlusion), halo_cells=halo, max_tan_off_nadir=vmax, seen_share=seen,
        units="DN", long_name=f"orthoimage ({get_kernel(params.kernel).label})",
    )
    return result


def _name(height: xr.DataArray) -> str:
    src = height.attrs.get("source_path") or height.name
    return f" {src}" if src else ""
