"""Copies of images carrying corrected RPC tags (bounded memory)."""

from __future__ import annotations

import warnings
from pathlib import Path

from tiledsm.geometry.rpc import RPC

__all__ = ["copy_with_rpc"]


def copy_with_rpc(src: str | Path, dst: str | Path, rpc: RPC, rows_per_step: int = 1024) -> Path:
    """Copy every band of ``src`` into a tiled GeoTIFF ``dst`` (same dtype
    and nodata, no geotransform/CRS: sensor geometry) whose RPC tags hold
    ``rpc``; ``rows_per_step`` rows at a time; written atomically.

    Pixel coordinates of ``dst`` are those of ``src`` (``rpc`` must be the
    camera of ``src``'s pixels, a crop's RPC for a crop).
    """
    import numpy as np
    import rasterio
    from rasterio.rpc import RPC as RioRPC
    from rasterio.windows import Window

    from tiledsm.io import atomic_path

    dst = Path(dst)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(src) as s:
            prof = dict(driver="GTiff", width=s.width, height=s.height, count=s.count, dtype=s.dtypes[0],
                        nodata=s.nodata, compress="deflate")
            if s.width >= 256 and s.height >= 256:
                prof.update(tiled=True, blockxsize=256, blockysize=256)
            if s.width * s.height * s.count * np.dtype(s.dtypes[0]).itemsize > 3_500_000_000:
                prof["BIGTIFF"] = "YES"
            with atomic_path(dst) as tmp, rasterio.Env(GDAL_PAM_ENABLED="NO"):
                with rasterio.open(tmp, "w", **prof) as d:
                    d.rpcs = RioRPC.from_gdal(rpc.to_gdal())
                    for r0 in range(0, s.height, rows_per_step):
                        w = Window(0, r0, s.width, min(rows_per_step, s.height - r0))
                        d.write(s.read(window=w), window=w)
    return dst
