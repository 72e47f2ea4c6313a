"""Camera models and ground geometry (RPC, grids, footprints, geoid)."""

from tiledsm.geometry.fit import FitReport, fit_rpc, fit_rpc_report
from tiledsm.geometry.footprint import (
    grid_for_footprint,
    ground_polygon,
    image_window,
    overlap_lonlat_bounds,
    overlap_polygon,
    polygon_area,
)
from tiledsm.geometry.geoid import ellipsoid_to_geoid, geoid_height, geoid_to_ellipsoid
from tiledsm.geometry.grid import GroundGrid, utm_crs
from tiledsm.geometry.rpc import RPC
from tiledsm.geometry.rpc_io import find_camera, read_rpc

__all__ = [
    "RPC",
    "FitReport",
    "fit_rpc",
    "fit_rpc_report",
    "find_camera",
    "read_rpc",
    "geoid_height",
    "geoid_to_ellipsoid",
    "ellipsoid_to_geoid",
    "GroundGrid",
    "utm_crs",
    "grid_for_footprint",
    "image_window",
    "ground_polygon",
    "overlap_lonlat_bounds",
    "overlap_polygon",
    "polygon_area",
]
