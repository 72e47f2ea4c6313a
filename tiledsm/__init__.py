"""tiledsm: tiled digital surface models from satellite and UAV scenes."""

import os

# GDAL's block cache defaults to 5 % of the machine's memory per process, memory
# no run plans for; capped before any GDAL read of this process (docs:
# decisions/gdal-cache.md). A user's own GDAL_CACHEMAX wins. Workers import
# tiledsm before their first task reads.
GDAL_CACHE_MB = 64
os.environ.setdefault("GDAL_CACHEMAX", str(GDAL_CACHE_MB))

# numba caches the compiled kernels (cache=True) beside their sources or in the
# user's cache; where neither can be written (a read-only installation, a user
# without a writable home) it would refuse to compile: point it at a folder of
# this user in the temporary folder instead, before numba is imported.
from tiledsm.writable import direct_numba_cache  # noqa: E402

direct_numba_cache(os.path.dirname(__file__))

# numba checks a cached kernel against its own file only: remove the kernels
# whose imported modules changed (an upgrade, an edit), before any is loaded.
from tiledsm.kernel_cache import purge_stale_kernels  # noqa: E402

purge_stale_kernels(os.path.dirname(__file__))

from tiledsm.errors import TiledsmError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["TiledsmError", "__version__"]
