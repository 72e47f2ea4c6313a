"""Put two DSMs on one ground grid, lazily.

The common grid is the **reference DSM's pixel grid** (its CRS, resolution
and pixel phase) cropped to the part of the ground both DSMs cover. The
reference is only cropped (never resampled). The other DSM is

- sliced, when it already lies on the same CRS, resolution and pixel phase
  (exact, no interpolation), or
- resampled block by block with GDAL's warper (``rasterio.warp.reproject``,
  bilinear by default, NaN-aware), each task reading only the source window
  its destination block needs.

Heights are float32 with NaN for "no height"; file nodata becomes NaN.
Pixel convention: GDAL's (transform maps the top-left *corner* of pixel
``[0, 0]``; xarray coordinates are cell centres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr
from affine import Affine

from tiledsm.errors import GridError, InputFileError, NoOverlapError

__all__ = ["open_dsm", "align_dsms", "onto_grid", "AlignedPair", "ReferenceGrid", "dsm_name"]

_EPS = 1e-6  # pixel tolerance when deciding two grids share a pixel phase


def dsm_name(dsm) -> str:
    """Name of a DSM for messages: its source file or ``attrs['source']``."""
    if isinstance(dsm, (str, Path)):
        return str(dsm)
    return str(dsm.attrs.get("source", dsm.name or "<in-memory DSM>"))


def open_dsm(path: str | Path, chunks: int = 1024) -> xr.DataArray:
    """Open a single-band DSM lazily (dask), nodata -> NaN, float32.

    Parameters
    ----------
    path : str or Path
        GeoTIFF (or any GDAL raster) or a zarr store written by
        :func:`tiledsm.io.write_zarr` holding one height variable.
    chunks : int
        Dask chunk edge in pixels.

    Raises
    ------
    InputFileError
        Missing or unreadable file, no CRS, or a rotated geotransform.
    """
    import rioxarray  # noqa: F401  (registers .rio)

    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: no such DSM file")
    if path.is_dir():
        from tiledsm.io import open_raster_product

        arr = open_raster_product(path)
    else:
        try:
            # lock=False: one file handle per thread instead of rioxarray's process-wide read lock, so the
            # workers decode their blocks' tiles in parallel (the lock serialised every read of the pass)
            arr = rioxarray.open_rasterio(path, chunks={"band": 1, "y": chunks, "x": chunks}, masked=True, lock=False)
        except Exception as exc:  # rasterio raises several types
            raise InputFileError(f"{path}: not a readable raster ({exc})") from exc
        if arr.sizes.get("band", 1) != 1:
            raise InputFileError(f"{path}: expected a single-band DSM, found {arr.sizes['band']} bands")
        arr = arr.squeeze("band", drop=True)
    if arr.rio.crs is None:
        raise InputFileError(f"{path}: DSM has no CRS (a georeferenced DSM is required)")
    arr = arr.astype(np.float32)
    arr.attrs = {"source": str(path)}
    check_grid(arr)
    return arr.chunk({"y": chunks, "x": chunks})


def check_grid(dsm: xr.DataArray) -> Affine:
    """The transform of ``dsm``; raises when it is rotated or degenerate."""
    t = dsm.rio.transform(recalc=True)
    if t.b != 0 or t.d != 0:
        raise GridError(f"{dsm_name(dsm)}: rotated geotransform {tuple(t)[:6]} is not supported")
    if t.a == 0 or t.e == 0:
        raise GridError(f"{dsm_name(dsm)}: degenerate geotransform {tuple(t)[:6]}")
    return t


@dataclass(frozen=True)
class ReferenceGrid:
    """The grid a comparison runs on: the reference DSM's own pixel grid, in
    its own CRS, **geographic included** (unlike
    :class:`tiledsm.geometry.grid.GroundGrid`, which is the projected grid a
    DSM is *made* on). Nothing is resampled onto a projected grid: the
    co-registration and slopes measure metres per cell row by row
    (:func:`tiledsm.compare.terrain.metric_steps`).

    Attributes
    ----------
    crs : rasterio.crs.CRS
    transform : affine.Affine
        GDAL corner convention, no rotation (cells may be non-square).
    shape : (int, int)
        ``(rows, cols)``.
    chunk : int
        Chunk edge of the comparison, cells.
    """

    crs: object
    transform: Affine
    shape: tuple[int, int]
    chunk: int

    @classmethod
    def of(cls, dsm: xr.DataArray, chunk: int) -> "ReferenceGrid":
        """The grid of an opened reference DSM (:func:`open_dsm`)."""
        return cls(dsm.rio.crs, check_grid(dsm), tuple(dsm.rio.shape), int(chunk))

    @property
    def height(self) -> int:
        return self.shape[0]

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(left, bottom, right, top)`` in the grid's CRS units."""
        from rasterio.transform import array_bounds

        west, south, east, north = array_bounds(self.height, self.width, self.transform)
        return (west, south, east, north)

    @property
    def numblocks(self) -> tuple[int, int]:
        return (-(-self.height // self.chunk), -(-self.width // self.chunk))

    def describe(self) -> str:
        """One line: CRS, cell size with its unit, shape, chunks, bounds."""
        unit = "°" if self.crs.is_geographic else " m"
        nby, nbx = self.numblocks
        return (f"{self.crs}, {abs(self.transform.a):.6g}{unit} x {abs(self.transform.e):.6g}{unit} cells, "
                f"{self.height} x {self.width} cells ({self.height * self.width / 1e6:.3g} Mcells), chunks of "
                f"{self.chunk}: {nby} x {nbx} = {nby * nbx}, bounds "
                + "(" + ", ".join(f"{v:.6g}" for v in self.bounds) + ")")


@dataclass(frozen=True)
class AlignedPair:
    """Two DSMs on one grid (lazy, dask-backed), with that grid's georeferencing.

    Attributes
    ----------
    ref, other : xr.DataArray
        float32 heights ``(y, x)``, NaN = no height, same shape and chunks.
    crs : rasterio.crs.CRS
    transform : affine.Affine
        Transform of the common grid (GDAL corner convention).
    ref_window : tuple of int
        ``(row0, row1, col0, col1)`` of the common grid in the reference DSM.
    resampled : bool
        False when ``other`` was sliced without interpolation.
    """

    ref: xr.DataArray
    other: xr.DataArray
    crs: object
    transform: Affine
    ref_window: tuple[int, int, int, int]
    resampled: bool


def _grid_array(data, transform: Affine, crs, name: str, source: str) -> xr.DataArray:
    h, w = data.shape
    x = transform.c + transform.a * (np.arange(w) + 0.5)
    y = transform.f + transform.e * (np.arange(h) + 0.5)
    arr = xr.DataArray(data, dims=("y", "x"), coords={"y": y, "x": x}, name=name, attrs={"source": source})
    return arr.rio.write_crs(crs).rio.write_transform(transform)


def align_dsms(ref: xr.DataArray, other: xr.DataArray, chunks: int = 1024, resampling: str = "bilinear") -> AlignedPair:
    """Crop ``ref`` and bring ``other`` onto ref's pixel grid over their overlap.

    Parameters
    ----------
    ref, other : xr.DataArray
        Georeferenced DSMs (``.rio.crs`` and transform set), e.g. from
        :func:`open_dsm`; may be dask-backed.
    chunks : int
        Chunk edge (pixels) of the aligned arrays.
    resampling : str
        ``rasterio.enums.Resampling`` name used when other must be resampled.

    Raises
    ------
    NoOverlapError
        When the DSMs have no ground in common (names both).
    """
    import rioxarray  # noqa: F401
    from rasterio.enums import Resampling
    from rasterio.warp import transform_bounds

    rt, ot = check_grid(ref), check_grid(other)
    rcrs, ocrs = ref.rio.crs, other.rio.crs
    rname, oname = dsm_name(ref), dsm_name(other)
    ob = other.rio.bounds(recalc=True)
    if ocrs != rcrs:
        ob = transform_bounds(ocrs, rcrs, *ob, densify_pts=21)
    # other's bounds in ref pixel coordinates (col, row), snapped outward
    inv = ~rt
    c_a, r_a = inv @ (ob[0], ob[3])
    c_b, r_b = inv @ (ob[2], ob[1])
    col0 = max(0, math.floor(min(c_a, c_b) + _EPS))
    col1 = min(ref.sizes["x"], math.ceil(max(c_a, c_b) - _EPS))
    row0 = max(0, math.floor(min(r_a, r_b) + _EPS))
    row1 = min(ref.sizes["y"], math.ceil(max(r_a, r_b) - _EPS))
    if col1 <= col0 or row1 <= row0:
        raise NoOverlapError(
            f"DSMs do not overlap: {rname} (bounds {tuple(round(v, 6) for v in ref.rio.bounds())}, {rcrs}) and "
            f"{oname} (bounds {tuple(round(v, 6) for v in other.rio.bounds())}, {ocrs})"
        )
    gt = rt @ Affine.translation(col0, row0)
    h, w = row1 - row0, col1 - col0
    ref_data = _as_dask(ref).data[row0:row1, col0:col1].rechunk(chunks)
    ref_al = _grid_array(ref_data, gt, rcrs, "ref", rname)

    same_phase = False
    if ocrs == rcrs and abs(ot.a - rt.a) < _EPS * abs(rt.a) and abs(ot.e - rt.e) < _EPS * abs(rt.e):
        oc, orr = (~ot) @ (gt.c, gt.f)  # common grid origin in other's pixels
        same_phase = abs(oc - round(oc)) < _EPS and abs(orr - round(orr)) < _EPS
    if same_phase:
        odata = _slice_padded(_as_dask(other).data, int(round(orr)), int(round(oc)), h, w).rechunk(ref_data.chunks)
    else:
        try:
            method = Resampling[resampling]
        except KeyError:
            raise GridError(f"unknown resampling {resampling!r}; one of {[m.name for m in Resampling]}") from None
        odata = _warp_lazy(_as_dask(other).data, ot, ocrs, gt, rcrs, ref_data.chunks, method)
    other_al = _grid_array(odata, gt, rcrs, "other", oname)
    return AlignedPair(ref_al, other_al, rcrs, gt, (row0, row1, col0, col1), not same_phase)


def onto_grid(src: xr.DataArray, like: xr.DataArray, resampling: str = "bilinear") -> xr.DataArray:
    """``src`` on the whole grid of ``like`` (its CRS, transform, shape and
    chunks), lazily: sliced when it shares ``like``'s CRS, cell size and
    pixel phase, else resampled block by block (:func:`align_dsms`'s
    warper: each task reads the source window its block needs). Cells
    ``src`` does not cover are NaN. float32; ``like`` in memory gives one
    block.

    Raises
    ------
    GridError
        Unknown ``resampling`` name, rotated or degenerate geotransform.
    """
    import rioxarray  # noqa: F401
    from rasterio.enums import Resampling

    st, gt = check_grid(src), check_grid(like)
    scrs, dcrs = src.rio.crs, like.rio.crs
    h, w = like.shape
    chunks = like.data.chunks if isinstance(like.data, da.Array) else ((h,), (w,))
    data = _as_dask(src).data
    same_phase = False
    if scrs == dcrs and abs(st.a - gt.a) < _EPS * abs(gt.a) and abs(st.e - gt.e) < _EPS * abs(gt.e):
        oc, orr = (~st) @ (gt.c, gt.f)  # like's origin in src's pixels
        same_phase = abs(oc - round(oc)) < _EPS and abs(orr - round(orr)) < _EPS
    if same_phase:
        out = _slice_padded(data, int(round(orr)), int(round(oc)), h, w).rechunk(chunks)
    else:
        try:
            method = Resampling[resampling]
        except KeyError:
            raise GridError(f"unknown resampling {resampling!r}; one of {[m.name for m in Resampling]}") from None
        out = _warp_lazy(data, st, scrs, gt, dcrs, chunks, method)
    arr = xr.DataArray(out, dims=("y", "x"), coords={"y": like.y, "x": like.x}, name=src.name,
                       attrs={"source": dsm_name(src)})
    return arr.rio.write_crs(dcrs).rio.write_transform(gt)


def _as_dask(arr: xr.DataArray) -> xr.DataArray:
    arr = arr.astype(np.float32)
    if not isinstance(arr.data, da.Array):
        arr = arr.chunk()
    return arr


def _slice_padded(src: da.Array, r0: int, c0: int, h: int, w: int) -> da.Array:
    """``src[r0:r0+h, c0:c0+w]`` with NaN where the window leaves ``src``."""
    H, W = src.shape
    rs, re_ = max(r0, 0), min(r0 + h, H)
    cs, ce = max(c0, 0), min(c0 + w, W)
    if rs >= re_ or cs >= ce:
        return da.full((h, w), np.nan, dtype=np.float32)
    core = src[rs:re_, cs:ce]
    pad = ((rs - r0, r0 + h - re_), (cs - c0, c0 + w - ce))
    if any(p for pair in pad for p in pair):
        core = da.pad(core, pad, mode="constant", constant_values=np.nan)
    return core


def _warp_block(src: np.ndarray, src_transform, src_crs, dst_transform, dst_crs, shape, method) -> np.ndarray:
    from rasterio.warp import reproject

    dst = np.full(shape, np.nan, dtype=np.float32)
    reproject(
        np.ascontiguousarray(src, dtype=np.float32),
        dst,
        src_transform=src_transform,
        src_crs=src_crs,
        src_nodata=np.nan,
        dst_transform=dst_transform,
        dst_crs=dst_crs,
        dst_nodata=np.nan,
        resampling=method,
        tolerance=0.0,  # exact transformer: blocks then agree with a whole-array warp
    )
    return dst


def _warp_lazy(src: da.Array, st: Affine, scrs, gt: Affine, dcrs, chunks, method, margin: int = 3) -> da.Array:
    """Resample ``src`` onto the grid ``gt`` block by block (one task per block)."""
    from rasterio.warp import transform_bounds

    H, W = src.shape
    rows = np.cumsum((0,) + chunks[0])
    cols = np.cumsum((0,) + chunks[1])
    blocks = []
    for i in range(len(chunks[0])):
        line = []
        for j in range(len(chunks[1])):
            shape = (int(rows[i + 1] - rows[i]), int(cols[j + 1] - cols[j]))
            bt = gt @ Affine.translation(cols[j], rows[i])
            x0, y0 = bt @ (0, 0)
            x1, y1 = bt @ (shape[1], shape[0])
            b = (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
            if scrs != dcrs:
                b = transform_bounds(dcrs, scrs, *b, densify_pts=21)
            ca, ra = (~st) @ (b[0], b[3])
            cb, rb = (~st) @ (b[2], b[1])
            sc0 = max(0, math.floor(min(ca, cb)) - margin)
            sc1 = min(W, math.ceil(max(ca, cb)) + margin)
            sr0 = max(0, math.floor(min(ra, rb)) - margin)
            sr1 = min(H, math.ceil(max(ra, rb)) + margin)
            if sc1 <= sc0 or sr1 <= sr0:
                line.append(da.full(shape, np.nan, dtype=np.float32))
                continue
            wt = st @ Affine.translation(sc0, sr0)
            task = dask.delayed(_warp_block, pure=True)(src[sr0:sr1, sc0:sc1], wt, scrs, bt, dcrs, shape, method)
            line.append(da.from_delayed(task, shape, dtype=np.float32))
        blocks.append(line)
    return da.block(blocks)
