"""Camera models and ground geometry (RPC, grids, footprints, geoid)."""

from tiledsm.geometry.fit import FitReport, fit_rpc, fit_rpc_report
from tiledsm.geometry.geoid import ellipsoid_to_geoid, geoid_height, geoid_to_ellipsoid
from tiledsm.geometry.rpc import RPC
from tiledsm.geometry.rpc_io import find_camera, read_rpc

__all__ = ["RPC", "FitReport", "fit_rpc", "fit_rpc_report", "find_camera", "read_rpc",
           "geoid_height", "geoid_to_ellipsoid", "ellipsoid_to_geoid"]
