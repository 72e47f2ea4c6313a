"""Ground grids of rasters and arrays on disk or in memory: the I/O side
of :class:`tiledsm.geometry.grid.GroundGrid`, which is pure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from tiledsm.errors import GridError, InputFileError
from tiledsm.geometry.grid import GroundGrid

__all__ = ["grid_like", "grid_array"]


def grid_like(ref, chunk: int | None = None) -> GroundGrid:
    """The grid of an existing raster (same CRS, transform and shape).

    Parameters
    ----------
    ref : str, Path or xarray.DataArray
        A georeferenced raster file (anything rasterio opens) or a
        DataArray with rioxarray CRS and transform.
    chunk : int, optional
        Chunk edge; default: the DataArray's first dask chunk along ``y``
        when it has one, else :data:`tiledsm.geometry.grid.DEFAULT_CHUNK`.

    Raises
    ------
    InputFileError
        The file cannot be opened.
    GridError
        No CRS, a rotated or non-square pixel grid, or a south-up grid
        (:meth:`GroundGrid.from_transform`).
    """
    if isinstance(ref, (str, Path)):
        import rasterio

        name = str(ref)
        try:
            with rasterio.open(ref) as src:
                crs, transform, shape = src.crs, src.transform, (src.height, src.width)
        except rasterio.errors.RasterioIOError as exc:
            raise InputFileError(f"{name}: cannot open as a raster ({exc})") from exc
    else:
        import rioxarray  # noqa: F401  (registers .rio)

        name = str(getattr(ref, "name", None) or "DataArray")
        crs, transform, shape = ref.rio.crs, ref.rio.transform(), ref.rio.shape
        if chunk is None and getattr(ref, "chunks", None):
            chunk = int(ref.chunks[ref.get_axis_num("y")][0])
    if crs is not None and crs.is_geographic:
        # GroundGrid's own refusal cannot name the raster; a DSM is made on a projected grid, a geographic
        # raster is only compared (tiledsm.compare.align.ReferenceGrid)
        raise GridError(f"{name}: CRS {crs} is geographic (degrees); a DSM grid needs a projected CRS in metres "
                        "(e.g. the local UTM zone): reproject the raster first")
    return GroundGrid.from_transform(crs, transform, shape, chunk, name)


def grid_array(grid: GroundGrid, dtype: str = "float32", fill: float = np.nan, name: str | None = None) -> xr.DataArray:
    """A lazy dask-backed DataArray on ``grid`` filled with ``fill``, CRS
    and transform written (rioxarray)."""
    import dask.array as dsa
    import rioxarray  # noqa: F401  (registers .rio)

    data = dsa.full(grid.shape, fill, dtype=dtype, chunks=grid.chunks)
    arr = xr.DataArray(data, dims=("y", "x"), coords=grid.coords(), name=name)
    return arr.rio.write_crs(grid.crs).rio.write_transform(grid.transform)
