"""DSM stage: images with RPCs -> a tiled, seamless DSM on a ground grid.

Dense matching happens in object space (semi-global vertical line locus,
:mod:`tiledsm.match.sgvll`): every dask task owns one chunk of the final
ground grid plus a halo, reads only the image windows its footprint needs,
matches, trims the halo and hands back its chunk. Chunks of neighbouring
tasks share one grid, so the mosaic has no seams by construction.

Coarse to fine: level ``L-1`` (coarsest, ground resolution ``res * 2**(L-1)``)
searches the whole scene height range; each finer level searches a few
height steps around the upsampled coarser DSM, per cell.

Conventions: heights are metres above the WGS84 ellipsoid (the RPCs'),
unless a geoid grid is given for the output; NaN means "no height".

The package: :mod:`.params` (:class:`DSMParams`), :mod:`.views` (images,
cameras, height range, default grid, footprints), :mod:`.levels` (one
pyramid level's geometry and the matching of one chunk), :mod:`.layout`
(a level's chunks, halos and depths), :mod:`.stages` (the engine: each
level matched into a store), :mod:`.engine` (the coarse-to-fine DSM, its
fingerprint) and :mod:`.products` (heights above a geoid).
"""

from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.views import View, default_grid, footprint_mask, open_views, read_window, scene_height_range
from tiledsm.dsm.layout import LevelLayout, level_chunks, level_layout, min_chunk
from tiledsm.dsm.levels import LevelGeometry, auto_levels, level_geometry, level_grid, match_cells
from tiledsm.dsm.engine import dsm_fingerprint, dsm_from_pair, dsm_from_views, prepare_views
from tiledsm.dsm.products import heights_above_geoid

__all__ = [
    "DSMParams",
    "View",
    "open_views",
    "read_window",
    "scene_height_range",
    "prepare_views",
    "default_grid",
    "footprint_mask",
    "LevelGeometry",
    "level_grid",
    "level_geometry",
    "level_chunks",
    "level_layout",
    "LevelLayout",
    "min_chunk",
    "match_cells",
    "auto_levels",
    "dsm_from_views",
    "dsm_fingerprint",
    "dsm_from_pair",
    "heights_above_geoid",
]
