"""Scenes and stores: open images with their camera, write products atomically,
and fill chunked zarr stores block by block with resume.

Conventions
-----------
- **Scenes** (:func:`open_scene`) are lazy, dask-backed ``float32``
  ``xarray.DataArray`` objects with nodata as NaN. Dims are ``(y, x)`` for
  one band, ``(band, y, x)`` otherwise. A scene in sensor geometry (no CRS:
  raw images, and crops whose geotransform only holds a pixel offset) has
  ``y``/``x`` coordinates equal to **pixel centres in the RPC/GDAL
  convention of this array**: ``y[i] = i + 0.5``, ``x[j] = j + 0.5`` (the
  top-left image corner is (0, 0)), so ``rpc.project`` output compares
  directly with them. A crop's offset is *not* added: the camera returned
  for a crop describes the crop. A georeferenced raster keeps its CRS
  coordinates (cell centres).
- The camera travels in ``attrs["rpc"]`` as GDAL's RPC metadata dict
  (``str -> str``, see :meth:`tiledsm.geometry.RPC.to_gdal`), which survives
  zarr attributes and GeoTIFF RPC tags; ``attrs["camera_source"]`` says where
  it came from and ``attrs["source_path"]`` which file the pixels came from.
- **Writes are atomic** (:func:`atomic_path`): every writer writes to a
  hidden temporary sibling and renames it onto the final name only when the
  write succeeded. A killed run leaves at most a hidden ``.NAME.tmp-*``
  sibling (and what its writer put beside it), never a half-written
  product under the final name; the next run that takes the folder's lock
  removes them (:func:`tiledsm.io.atomic.sweep_temporaries`). Paths are
  local (POSIX rename); object stores are not supported by the writers.
- **Resumable stores** (:func:`create_store`, :class:`ChunkStore`,
  :func:`write_blocks`): a stage's output grid is a zarr v3 store whose
  chunks are the stage's blocks. Each dask task writes its own block and
  then sets that block's completion marker; the client never gathers the
  array. While incomplete the store lives at ``NAME.partial``; when every
  marker is set :meth:`ChunkStore.finalize` renames it to ``NAME``.
  Completion is tracked by the uint8 zarr array ``_progress/done`` of shape
  ``numblocks`` with one zarr chunk per element (one file per block, so
  concurrent tasks never write the same file); a marker is written only
  after the block's data, so a task killed mid-write leaves its block
  pending and it is recomputed on resume. xarray ignores the ``_progress``
  sub-group when reading the store.

The package: :mod:`.atomic` (atomic writes), :mod:`.blockfiles` (a grid's
blocks as files, written by many threads at once), :mod:`.cameras` (RPC files read
and written, camera discovery), :mod:`.geoid` (geoid grids), :mod:`.grids`
(the ground grid of a raster), :mod:`.opened` (zarr arrays opened once per
process), :mod:`.scenes` (images and their cameras), :mod:`.stores` (zarr
products and resumable stores) and :mod:`.export` (GeoTIFF/COG).
"""

from tiledsm.io.cameras import find_camera, read_rpc
from tiledsm.io.grids import grid_like
from tiledsm.io.scenes import open_scene, scene_rpc
from tiledsm.io.atomic import atomic_path, withdraw
from tiledsm.io.stores import write_zarr, open_product, open_raster_product, ChunkStore, create_store, write_blocks, write_resumable
from tiledsm.io.opened import open_store_array
from tiledsm.io.blockfiles import BlockFiles
from tiledsm.io.export import exports_alongside, write_cog, write_geotiff_with_rpc

__all__ = [
    "find_camera",
    "read_rpc",
    "grid_like",
    "open_scene",
    "scene_rpc",
    "atomic_path",
    "withdraw",
    "write_zarr",
    "open_product",
    "open_raster_product",
    "write_cog",
    "write_geotiff_with_rpc",
    "ChunkStore",
    "create_store",
    "write_blocks",
    "write_resumable",
    "open_store_array",
    "BlockFiles",
]
