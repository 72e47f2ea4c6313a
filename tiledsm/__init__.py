"""tiledsm: tiled digital surface models from satellite and UAV scenes."""

from tiledsm.errors import TiledsmError

__version__ = "0.1.0"
__all__ = ["TiledsmError", "__version__"]
