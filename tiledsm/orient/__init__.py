"""Sensor orientation: tie-point tracks, P2L mismatch detection, and the
bias-compensated RPC block adjustment with GCPs and a reference DEM.

Pure kernels (:mod:`~tiledsm.orient.bias`, :mod:`~tiledsm.orient.adjust`,
:mod:`~tiledsm.orient.p2l`) work on arrays; :mod:`~tiledsm.orient.tracks`
tiles the matching with dask; :mod:`~tiledsm.orient.stage` reads the inputs
and writes the corrected RPCs.
"""

from tiledsm.orient.adjust import AdjustParams, AdjustResult, Block, adjust_block, intersect
from tiledsm.orient.bias import MODELS, BiasModel, choose_model, get_model
from tiledsm.orient.dem import ReferenceDEM
from tiledsm.orient.p2l import P2LParams, P2LResult, p2l_distances, p2l_filter, ransac_filter
from tiledsm.orient.points import ControlPoints, read_points
from tiledsm.orient.spec import OrientSpec, orient_for_recipe, polygon_exclusion
from tiledsm.orient.stage import Orientation, OrientParams, orient_images, write_orientation
from tiledsm.orient.tracks import Guide, TrackParams, Tracks, coarse_guide, tie_point_tracks

__all__ = [
    "AdjustParams", "AdjustResult", "Block", "adjust_block", "intersect",
    "MODELS", "BiasModel", "choose_model", "get_model",
    "ReferenceDEM",
    "P2LParams", "P2LResult", "p2l_distances", "p2l_filter", "ransac_filter",
    "ControlPoints", "read_points",
    "OrientSpec", "orient_for_recipe", "polygon_exclusion",
    "Orientation", "OrientParams", "orient_images", "write_orientation",
    "Guide", "TrackParams", "Tracks", "coarse_guide", "tie_point_tracks",
]
