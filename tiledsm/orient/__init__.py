"""Sensor orientation: tie-point tracks, P2L mismatch detection, and the
bias-compensated RPC block adjustment with GCPs and a reference DEM.

Pure kernels (:mod:`~tiledsm.orient.bias`, :mod:`~tiledsm.orient.adjust`,
:mod:`~tiledsm.orient.p2l`) work on arrays; :mod:`~tiledsm.orient.tracks`
tiles the matching with dask; :mod:`~tiledsm.orient.stage` reads the inputs
and writes the corrected RPCs. The stage (``pipeline: orient``, ``tiledsm
orient``): its recipe (:mod:`~tiledsm.orient.recipe`; parameters
:mod:`~tiledsm.orient.spec`, the functions' parameters too), plan
(:mod:`~tiledsm.orient.plan`) and runner (:mod:`~tiledsm.orient.run`); the
``orient:`` of a ``dsm`` or ``deformation`` recipe runs
:mod:`~tiledsm.orient.step`.

The package's names are loaded from their modules on first use (PEP 562):
a recipe model needs :class:`~tiledsm.orient.spec.OrientSpec`, not the
adjustment and its scipy.optimize (about 0.2 s of the start-up of every
``tiledsm dsm``).
"""

from __future__ import annotations

import importlib

#: the module of each name the package exports
_HOME = {name: module for module, names in (
    ("adjust", ("AdjustResult", "Block", "adjust_block", "intersect")),
    ("bias", ("MODELS", "BiasModel", "choose_model", "get_model")),
    ("dem", ("ReferenceDEM",)),
    ("p2l", ("P2LResult", "p2l_distances", "p2l_filter", "ransac_filter")),
    ("points", ("ControlPoints", "read_points")),
    ("recipe", ("OrientRecipe",)),
    ("spec", ("OrientSpec", "TrackParams", "StructuralParams", "P2LParams", "AdjustParams")),
    ("step", ("orient_for_recipe", "polygon_exclusion")),
    ("stage", ("Orientation", "orient_images", "write_orientation")),
    ("tracks", ("Guide", "Tracks", "coarse_guide", "tie_point_tracks")),
) for name in names}

__all__ = list(_HOME)


def __getattr__(name: str):
    module = _HOME.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
