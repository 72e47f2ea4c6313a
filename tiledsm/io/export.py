"""GeoTIFF exports: cloud-optimised GeoTIFFs and rasters carrying RPC tags."""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Mapping

import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from tiledsm.geometry.rpc import RPC
from tiledsm.io.atomic import remove_path, atomic_path
from tiledsm.io.overviews import average_2x2, cog_overview_count, streamable_overviews
from tiledsm.io.scenes import scene_rpc


# --------------------------------------------------------------------------- GeoTIFF
def _tag_value(v) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    if isinstance(v, np.generic):
        return str(v.item())
    return str(v)




#: seconds a COG export waits between its uncompressed source and the COG (tests set it to kill a run there)
EXPORT_PAUSE_ENV = "TILEDSM_TEST_EXPORT_PAUSE_S"


def _pause_for_tests() -> None:
    import time

    time.sleep(float(os.environ.get(EXPORT_PAUSE_ENV) or 0))


def _cache_mb() -> int:
    """The GDAL block cache of exports, MiB: the process's ``GDAL_CACHEMAX``
    (set by :mod:`tiledsm` unless the user set it). Set on the ``Env`` too,
    since a GDAL that initialised its cache earlier in the process ignores
    a later environment variable (measured on an 8192² COG export: process
    peak 638 MiB with GDAL's default cache, 320-370 MiB capped anywhere
    between 32 and 256 MiB, of which 162 MiB are the imports; same time)."""
    try:
        return int(os.environ.get("GDAL_CACHEMAX", "64"))
    except ValueError:  # a user's "5%" or "1GB": leave it to GDAL
        return 64


def _write_gtiff(
    data,
    path: Path,
    *,
    dtype,
    nodata,
    transform=None,
    crs=None,
    rpc: RPC | None = None,
    tags: Mapping | None = None,
    tiled: bool = True,
    compress: str | None = "DEFLATE",
    blocksize: int = 512,
    row_step: int | None = None,
    overviews: "OverviewWriter | None" = None,
) -> None:
    """Write a 2-D/3-D numpy or dask array to a GTiff, one dask block row at
    a time (bounded memory: one strip of blocks), or ``row_step`` rows at a
    time; each strip also goes to ``overviews`` (its levels averaged)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.rpc import RPC as RioRPC
    from rasterio.windows import Window

    arr = data
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ValueError(f"{path}: expected a 2-D (y, x) or 3-D (band, y, x) array, got shape {data.shape}")
    nb, ny, nx = (int(s) for s in arr.shape)
    profile = dict(driver="GTiff", width=nx, height=ny, count=nb, dtype=np.dtype(dtype).name, nodata=nodata)
    if transform is not None:
        profile["transform"] = transform
    if crs is not None:
        profile["crs"] = crs
    if tiled and nx >= 16 and ny >= 16:
        bs = max(16, min(int(blocksize), 1 << int(math.log2(max(min(nx, ny), 16)))) // 16 * 16)
        profile.update(tiled=True, blockxsize=bs, blockysize=bs)
    if compress:
        profile["compress"] = compress
    if nx * ny * nb * np.dtype(dtype).itemsize > 3_500_000_000:
        profile["BIGTIFF"] = "YES"
    is_dask = hasattr(arr, "dask")
    steps = arr.chunks[1] if is_dask else (ny,)
    if row_step:
        steps = (row_step,) * (ny // row_step) + ((ny % row_step,) if ny % row_step else ())
    with rasterio.Env(GDAL_PAM_ENABLED="NO", GDAL_CACHEMAX=_cache_mb()), warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", **profile) as dst:
            if rpc is not None:
                dst.rpcs = RioRPC.from_gdal(rpc.to_gdal())
            if tags:
                dst.update_tags(**{str(k): _tag_value(v) for k, v in tags.items()})
            r0 = 0
            for h in steps:
                block = np.asarray(arr[:, r0 : r0 + h, :].compute() if is_dask else arr[:, r0 : r0 + h, :])
                block = block.astype(dtype, copy=False)
                dst.write(block, window=Window(0, r0, nx, h))
                if overviews is not None:
                    overviews.write(block[0], r0)
                r0 += h


class OverviewWriter:
    """The COG overview levels of a 2-D float grid, averaged strip by strip
    (:func:`tiledsm.io.overviews.average_2x2`) into one uncompressed GTiff
    per level (``paths[k]``: factor ``2**(k+1)``), as the grid is written.

    Strips must start on rows divisible by ``2**len(paths)`` and hold a
    multiple of that many rows (the last one too), and the columns be a
    multiple of it: each level then halves whole cell pairs.
    Use as a context manager (the files are closed on exit).
    """

    def __init__(self, paths: list[Path], shape: tuple[int, int], dtype, blocksize: int = 512) -> None:
        import rasterio
        from rasterio.errors import NotGeoreferencedWarning

        self.paths = list(paths)
        ny, nx = shape
        self._dst = []
        tile = max(16, blocksize // 16 * 16)  # GTiff tiles are multiples of 16
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            for k, p in enumerate(self.paths, start=1):
                self._dst.append(rasterio.open(p, "w", driver="GTiff", width=nx >> k, height=ny >> k, count=1,
                                               dtype=np.dtype(dtype).name, nodata=float("nan"), tiled=True,
                                               blockxsize=tile, blockysize=tile))

    def write(self, strip: np.ndarray, r0: int) -> None:
        """Average ``strip`` (rows ``r0 : r0 + len(strip)`` of the grid) into every level."""
        from rasterio.windows import Window

        level = strip
        for k, dst in enumerate(self._dst, start=1):
            level = average_2x2(level)
            dst.write(level, 1, window=Window(0, r0 >> k, level.shape[1], level.shape[0]))

    def __enter__(self) -> "OverviewWriter":
        return self

    def __exit__(self, *exc) -> None:
        for dst in self._dst:
            dst.close()


def _vrt_with_overviews(src: Path, overviews: list[Path], vrt: Path) -> Path:
    """A VRT of ``src`` (GDAL's copy: georeferencing, nodata, tags) whose band
    lists ``overviews`` as its overview levels, which the ``COG`` driver then
    copies instead of computing its own."""
    import xml.etree.ElementTree as ET

    import rasterio.shutil

    rasterio.shutil.copy(src, vrt, driver="VRT")
    tree = ET.parse(vrt)
    band = tree.getroot().find("VRTRasterBand")
    for p in overviews:
        ov = ET.SubElement(band, "Overview")
        ET.SubElement(ov, "SourceFilename", relativeToVRT="0").text = str(p)
        ET.SubElement(ov, "SourceBand").text = "1"
    tree.write(vrt)
    return vrt


@contextlib.contextmanager
def exports_alongside(exports: Mapping[str, Callable[[], object]]) -> Iterator[dict[str, float]]:
    """Run each export in a thread of its own while the ``with`` body runs.

    GDAL compresses a COG's tiles and the compiled kernels average its
    overviews without the GIL, so an export overlaps with the caller's
    work (drawing figures, scoring) instead of adding to it.

    Parameters
    ----------
    exports : mapping of str to callable
        Name -> a call without arguments that writes one product.

    Yields
    ------
    dict of str to float
        Filled on leaving the body, once every export has finished: each
        one's seconds. An export's exception is raised there.
    """
    seconds: dict[str, float] = {}
    if not exports:
        yield seconds
        return

    def timed(write: Callable[[], object]) -> float:
        t0 = time.perf_counter()
        write()
        return time.perf_counter() - t0

    with ThreadPoolExecutor(max_workers=len(exports), thread_name_prefix="tiledsm-export") as pool:
        running = {name: pool.submit(timed, write) for name, write in exports.items()}
        yield seconds
        for name, future in running.items():
            seconds[name] = future.result()


def write_geotiff_with_rpc(
    array,
    path: str | os.PathLike,
    rpc: RPC,
    nodata: float | None = None,
    dtype=None,
    tags: Mapping | None = None,
) -> Path:
    """Write an image in sensor geometry as a GeoTIFF with RPC tags, atomically.

    GDAL writes the RPC into the TIFF ``RPCCoefficientTag``, which GDAL,
    rasterio (``src.rpcs``) and :func:`open_scene` read back.

    Parameters
    ----------
    array : numpy or dask array, or DataArray
        ``(y, x)`` or ``(band, y, x)``; dask arrays are written one block
        row at a time.
    path : path-like
    rpc : RPC
        Camera of this array (GDAL pixel convention).
    nodata : float, optional
        Nodata value stored in the file.
    dtype : dtype, optional
        Output dtype (default: the array's); values are cast (no rounding or
        clipping is done: round before writing integers).
    tags : mapping, optional
        Extra GDAL metadata tags (values stringified; dicts as JSON).
    """
    data = array.data if isinstance(array, xr.DataArray) else array
    dtype = np.dtype(dtype or data.dtype)
    final = Path(path)
    with atomic_path(final) as tmp:
        _write_gtiff(data, tmp, dtype=dtype, nodata=nodata, rpc=rpc, tags=tags)
    return final


def write_cog(
    da: xr.DataArray,
    path: str | os.PathLike,
    *,
    dtype="float32",
    nodata: float | None = float("nan"),
    compress: str = "DEFLATE",
    blocksize: int = 512,
    resampling: str = "AVERAGE",
    threads: str | int = "ALL_CPUS",
    level: int | None = None,
    overviews: str = "stream",
) -> Path:
    """Export a DataArray as a Cloud-Optimised GeoTIFF, atomically.

    The data are streamed (one dask block row at a time) to a temporary
    tiled GeoTIFF, then converted with GDAL's ``COG`` driver (overviews,
    ``resampling``), and renamed onto ``path``.

    Parameters
    ----------
    da : DataArray
        ``(y, x)`` or ``(band, y, x)`` with rioxarray CRS/transform; in
        sensor geometry (no CRS) a camera in ``attrs["rpc"]`` is written as
        RPC tags.
    path : path-like
    dtype : dtype
        Output dtype.
    nodata : float or None
        Nodata (NaN for float products).
    compress, blocksize, resampling : str, int, str
        COG creation options.
    threads : str or int
        GDAL's ``NUM_THREADS`` for compressing the tiles (``"ALL_CPUS"``
        or a count): tiles are compressed independently, so the file is
        byte-identical to a single-threaded one (tested); 1.4x faster on
        2 cores at 8192², DEFLATE level 1 (``benchmarks/cog.py``, ``cog.json``).
    level : int, optional
        Compression level (DEFLATE 1-12, ZSTD 1-22; GDAL's default when None).
    overviews : {"stream", "gdal"}
        ``"stream"``: where GDAL's ``AVERAGE`` overviews are 2 x 2 means
        (a 2-D float grid with NaN nodata whose sides are divisible by
        ``2**levels``), they are averaged while the source is streamed
        (:class:`OverviewWriter`) and handed to the ``COG`` driver, which
        otherwise reads the whole grid again to compute them: the same
        values, bit for bit, in less time (``benchmarks/cog.py`` times
        both routes); any other grid falls back to GDAL's. ``"gdal"``: always GDAL's.
    """
    import rasterio
    import rasterio.shutil
    if overviews not in ("stream", "gdal"):
        raise ValueError(f"write_cog: overviews must be 'stream' or 'gdal', got {overviews!r}")
    if da.ndim not in (2, 3) or da.dims[-2:] != ("y", "x"):
        raise ValueError(f"write_cog: expected dims (y, x) or (band, y, x), got {da.dims}")
    crs = da.rio.crs
    transform = da.rio.transform() if crs is not None else None
    rpc = scene_rpc(da) if (crs is None and "rpc" in da.attrs) else None
    tags = {k: v for k, v in da.attrs.items() if k != "rpc"}
    final = Path(path)
    dt = np.dtype(dtype)
    opts = dict(COMPRESS=compress, BLOCKSIZE=str(blocksize), OVERVIEW_RESAMPLING=resampling, NUM_THREADS=str(threads))
    if compress.upper() in ("DEFLATE", "LZW", "ZSTD"):
        opts["PREDICTOR"] = "FLOATING_POINT" if dt.kind == "f" else "YES"
    if level is not None:
        opts["LEVEL"] = str(level)
    shape = tuple(int(v) for v in da.shape[-2:])
    levels = cog_overview_count(shape, blocksize)
    own = (overviews == "stream" and da.ndim == 2 and resampling.upper() == "AVERAGE" and levels > 0
           and nodata is not None and math.isnan(nodata) and streamable_overviews(shape, dt, levels))
    with atomic_path(final) as tmp:
        src = Path(str(tmp) + ".src.tif")
        ovr = [Path(f"{tmp}.ovr{k}.tif") for k in range(1, levels + 1)] if own else []
        vrt = Path(str(tmp) + ".vrt")
        try:
            with OverviewWriter(ovr, shape, dt, blocksize) if own else contextlib.nullcontext() as writer:
                f = 1 << levels
                step = f * math.ceil(max(da.data.chunks[-2]) / f) if own and hasattr(da.data, "chunks") else None
                _write_gtiff(
                    da.data, src, dtype=dt, nodata=nodata, transform=transform, crs=crs, rpc=rpc, tags=tags,
                    compress=None, blocksize=blocksize, row_step=step, overviews=writer,
                )
            _pause_for_tests()
            with rasterio.Env(GDAL_PAM_ENABLED="NO", GDAL_CACHEMAX=_cache_mb()):
                source = _vrt_with_overviews(src, ovr, vrt) if own else src
                rasterio.shutil.copy(source, tmp, driver="COG", **opts)
        finally:
            for p in (src, vrt, *ovr):
                remove_path(p)
    return final


