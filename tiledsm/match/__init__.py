"""Dense matching kernels: costs, semi-global aggregation, object-space
SGVLL matching, triangulation and tie points (the image-space matcher that
validates the cost and the aggregation on Middlebury lives with its test,
``tests/match/stereo.py``).

Everything here works on in-memory numpy blocks; the dask orchestration
lives in :mod:`tiledsm.dsm`. The names below are imported from their
modules when first used: the parameter models (:mod:`.params`) load
without numba and OpenCV, so recipes and option errors come at once.
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module that defines it
_HOMES = {
    "zncc_cost": "cost",
    "mean_zncc_cost": "cost",
    "aggregate": "sgm",
    "winner_take_all": "sgm",
    "remove_speckles": "sgm",
    "SGVLLParams": "params",
    "height_step": "sgvll",
    "match_block": "sgvll",
    "SearchParams": "pyramid",
    "downsample": "pyramid",
    "search_from_coarse": "pyramid",
    "triangulate": "triangulate",
    "match_tiepoints": "tiepoints",
    "height_range_from_tiepoints": "tiepoints",
    "relative_correction": "tiepoints",
}

__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
