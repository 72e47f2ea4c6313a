"""tiledsm: tiled digital surface models from satellite and UAV scenes."""

import os

# GDAL's block cache defaults to 5 % of the machine's memory per process (1.2 GB
# here, 6 GB on a 128 GB node): every worker reading image windows and the client
# exporting a COG filled it (a 16384² DSM run: 828 MiB planned per worker, 2146
# measured). Capped before any GDAL read of this process; a user's own
# GDAL_CACHEMAX wins. Workers import tiledsm before their first task reads.
GDAL_CACHE_MB = 64
os.environ.setdefault("GDAL_CACHEMAX", str(GDAL_CACHE_MB))

from tiledsm.errors import TiledsmError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["TiledsmError", "__version__"]
