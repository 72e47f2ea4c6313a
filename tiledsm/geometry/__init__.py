"""Camera models and ground geometry (RPC, grids, footprints, geoid)."""

from tiledsm.geometry.rpc import RPC

__all__ = ["RPC"]
