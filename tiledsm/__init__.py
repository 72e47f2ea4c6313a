"""tiledsm: tiled digital surface models from satellite and UAV scenes."""

import os

# GDAL's block cache defaults to 5 % of the machine's memory per process, memory
# no run plans for; capped before any GDAL read of this process (docs:
# decisions/gdal-cache.md). A user's own GDAL_CACHEMAX wins. Workers import
# tiledsm before their first task reads.
GDAL_CACHE_MB = 64
os.environ.setdefault("GDAL_CACHEMAX", str(GDAL_CACHE_MB))

from tiledsm.errors import TiledsmError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["TiledsmError", "__version__"]
