"""Dense matching kernels: costs, semi-global aggregation, object-space
SGVLL matching, triangulation and tie points (the image-space matcher that
validates the cost and the aggregation on Middlebury lives with its test,
``tests/match/stereo.py``).

Everything here works on in-memory numpy blocks; the dask orchestration
lives in :mod:`tiledsm.dsm`.
"""

from tiledsm.match.cost import mean_zncc_cost, zncc_cost
from tiledsm.match.sgm import aggregate, remove_speckles, winner_take_all
from tiledsm.match.pyramid import SearchParams, downsample, search_from_coarse
from tiledsm.match.sgvll import SGVLLParams, height_step, match_block
from tiledsm.match.tiepoints import height_range_from_tiepoints, match_tiepoints, relative_correction
from tiledsm.match.triangulate import triangulate

__all__ = [
    "zncc_cost",
    "mean_zncc_cost",
    "aggregate",
    "winner_take_all",
    "remove_speckles",
    "SGVLLParams",
    "height_step",
    "match_block",
    "SearchParams",
    "downsample",
    "search_from_coarse",
    "triangulate",
    "match_tiepoints",
    "height_range_from_tiepoints",
    "relative_correction",
]
