"""Scenes: images opened lazily with their camera (RPC tags, sidecars)."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from tiledsm.errors import InputFileError, RPCError, UnsupportedFormatError
from tiledsm.geometry.rpc import RPC


# --------------------------------------------------------------------------- scenes
def _find_camera(image_path: Path, rpc) -> tuple[RPC, str]:
    """Camera of an image: :func:`tiledsm.io.cameras.find_camera`."""
    if isinstance(rpc, RPC):
        return rpc, rpc.source or "RPC object given"
    from tiledsm.io.cameras import find_camera  # lazy: keeps tiledsm.io import light

    return find_camera(image_path, rpc)


def open_scene(
    path: str | os.PathLike,
    chunks: int | str | Mapping[str, int] = 1024,
    rpc: "RPC | str | os.PathLike | None" = None,
    band: int | None = None,
    require_camera: bool = True,
) -> xr.DataArray:
    """Open an image lazily with its camera.

    Parameters
    ----------
    path : path-like
        Any raster GDAL reads (GeoTIFF, NITF, JP2...).
    chunks : int, "auto" or dict
        Dask chunk edge in pixels (``y`` and ``x``), or a dict per dim.
        Bands are kept in one chunk.
    rpc : RPC, path-like or None
        Explicit camera: an :class:`RPC` or a file holding one. Default:
        from the image itself or a same-stem sidecar (``.geom``, ``.RPB``,
        ``_RPC.TXT``, ``.XML``), see ``tiledsm.io.cameras.find_camera``.
    band : int, optional
        1-based band to select (dims then ``(y, x)``).
    require_camera : bool
        When False, a raster without camera opens anyway (no ``rpc`` attr),
        e.g. a DSM.

    Returns
    -------
    xarray.DataArray
        ``float32`` dask-backed, nodata as NaN, dims ``(y, x)`` or
        ``(band, y, x)``; coordinates: see the module conventions. Attrs:
        ``rpc`` (GDAL RPC dict), ``camera_source``, ``source_path``, plus the
        file's own metadata tags.

    Raises
    ------
    InputFileError
        Missing or unreadable file (:class:`UnsupportedFormatError` when GDAL
        does not recognise it).
    RPCError
        No camera found (when ``require_camera``) or a garbled one.
    """
    import rasterio
    from affine import Affine
    from rasterio.errors import NotGeoreferencedWarning

    p = Path(path)
    if not p.exists():
        raise InputFileError(f"{p}: no such file")
    if not p.is_file():
        raise InputFileError(f"{p}: not a file")
    ch = {"y": chunks, "x": chunks} if isinstance(chunks, (int, str)) else dict(chunks)
    ch.setdefault("band", -1)
    try:
        with warnings.catch_warnings():  # sensor-geometry images have no geotransform by design
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            da = rioxarray.open_rasterio(p, chunks=ch, masked=True, mask_and_scale=True)
    except rasterio.errors.RasterioIOError as exc:
        msg = str(exc)
        cls = UnsupportedFormatError if "not recognized" in msg or "supported file format" in msg else InputFileError
        raise cls(f"{p}: cannot open as a raster ({msg})") from exc
    if isinstance(da, list) or isinstance(da, xr.Dataset):
        raise UnsupportedFormatError(f"{p}: holds several subdatasets; open one of them")
    if band is not None:
        if band not in da.band.values:
            raise InputFileError(f"{p}: has no band {band} (bands {list(map(int, da.band.values))})")
        da = da.sel(band=band, drop=True)
    elif da.sizes["band"] == 1:
        da = da.squeeze("band", drop=True)
    if da.dtype != np.float32:
        da = da.astype(np.float32)
    attrs = {k: v for k, v in da.attrs.items() if k not in ("scale_factor", "add_offset", "_FillValue")}
    if da.rio.crs is None:
        ny, nx = da.sizes["y"], da.sizes["x"]
        da = da.assign_coords(y=np.arange(ny) + 0.5, x=np.arange(nx) + 0.5)
        da = da.rio.write_transform(Affine.identity())
    try:
        camera, desc = _find_camera(p, rpc)
    except RPCError:
        if rpc is not None or require_camera:
            raise
    else:
        attrs["rpc"] = camera.to_gdal()
        attrs["camera_source"] = desc
    attrs["source_path"] = str(p.resolve())
    da.attrs = attrs
    da.encoding = {"source": str(p)}
    da.name = da.name or p.stem
    return da


def scene_rpc(da: xr.DataArray) -> RPC:
    """The camera stored in a scene's attrs (see :func:`open_scene`).

    Raises
    ------
    RPCError
        The DataArray carries no ``rpc`` attribute (message names its source).
    """
    md = da.attrs.get("rpc")
    src = da.attrs.get("source_path") or da.name or "DataArray"
    if md is None:
        raise RPCError(f"{src}: no camera in attrs['rpc']")
    if isinstance(md, str):  # flattened by a format that stores strings only
        md = json.loads(md)
    return RPC.from_gdal(md, source=str(da.attrs.get("camera_source") or src))


# --------------------------------------------------------------------------- windows
def read_window(path: str | os.PathLike, r0: int, r1: int, c0: int, c1: int, band: int = 1) -> np.ndarray:
    """Rows ``r0:r1`` and columns ``c0:c1`` of a raster band as float32,
    NaN outside the raster and on nodata (boundless read; array indices,
    row 0 the image's first line)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.windows import Window

    out = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            rr0, rr1, cc0, cc1 = max(r0, 0), min(r1, ds.height), max(c0, 0), min(c1, ds.width)
            if rr1 > rr0 and cc1 > cc0:
                a = ds.read(band, window=Window(cc0, rr0, cc1 - cc0, rr1 - rr0), masked=True)
                out[rr0 - r0: rr1 - r0, cc0 - c0: cc1 - c0] = a.astype(np.float32).filled(np.nan)
    return out
