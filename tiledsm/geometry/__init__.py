"""Camera models and ground geometry (RPC, its fitting, grids, footprints):
pure functions on arrays, no file and no dask graph (reading cameras and
grids from files is :mod:`tiledsm.io`'s)."""

from tiledsm.geometry.fit import FitReport, fit_rpc, fit_rpc_report, with_affine
from tiledsm.geometry.footprint import (
    grid_for_footprint,
    ground_polygon,
    image_window,
    overlap_lonlat_bounds,
    overlap_polygon,
    polygon_area,
)
from tiledsm.geometry.grid import GroundGrid, utm_crs
from tiledsm.geometry.rpc import RPC

__all__ = [
    "RPC",
    "FitReport",
    "fit_rpc",
    "fit_rpc_report",
    "with_affine",
    "GroundGrid",
    "utm_crs",
    "grid_for_footprint",
    "image_window",
    "ground_polygon",
    "overlap_lonlat_bounds",
    "overlap_polygon",
    "polygon_area",
]
