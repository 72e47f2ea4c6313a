"""The ``dh`` Cloud-Optimised GeoTIFF, converted from the comparison's zarr store.

:func:`cog_from_store` streams the stored ``dh`` (one row of zarr chunks at a
time, read in this process: the chunks are already computed, so no task
graph and no worker is involved) through :func:`tiledsm.io.write_cog`, with
GDAL's compression threads on every core (the workers are idle by then) and
its block cache bounded, so the process never holds more than a row of
chunks plus ``cache_mib`` whatever the grid size. The overviews are averaged
from the rows as they stream by (:func:`tiledsm.io.write_cog`: the values GDAL
computes, without reading the grid again), and the tiles are DEFLATE level
:data:`DH_DEFLATE_LEVEL`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import dask
import numpy as np
import xarray as xr

__all__ = ["DH_DEFLATE_LEVEL", "cog_from_store", "jsonable"]

#: DEFLATE level of ``dh.tif``. Measured on the 8192² benchmark's dh (2 cores):
#: level 1 compresses in 1.9 s of CPU into 31.3 MiB, GDAL's default (6) in 6.5 s
#: into 28.3 MiB; the export is on the command's critical path, the bytes are not.
DH_DEFLATE_LEVEL = 1


def cog_from_store(dh: xr.DataArray, path: str | os.PathLike, *, threads: str | int = "ALL_CPUS", cache_mib: int = 256) -> Path:
    """Write ``dh`` (a DataArray opened lazily from a zarr store) as a COG.

    Parameters
    ----------
    dh : xarray.DataArray
        ``(y, x)`` float32 heights differences (metres, NaN = none) with CRS
        and transform, dask-backed by a zarr store.
    path : path-like
        The ``.tif`` to write (atomically, by :func:`tiledsm.io.write_cog`).
    threads : int or "ALL_CPUS"
        GDAL compression threads (``GDAL_NUM_THREADS``).
    cache_mib : int
        GDAL block cache (``GDAL_CACHEMAX``, MiB): bounds the memory of the
        overview computation.
    """
    import rasterio

    from tiledsm.io import write_cog

    with rasterio.Env(GDAL_NUM_THREADS=str(threads), GDAL_CACHEMAX=int(cache_mib)), dask.config.set(scheduler="threads"):
        return write_cog(dh, path, level=DH_DEFLATE_LEVEL)


def jsonable(obj):
    """``obj`` with numpy scalars, paths and tuples made JSON values (a non-finite float: ``None``)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj
