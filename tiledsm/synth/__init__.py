"""Synthetic scenes with known truth (terrain, buildings, trees, texture,
pushbroom views with RPCs, occlusion-aware rendering, degradations, and a
post-event version with a known displacement field).

Public API: :func:`make_scene` -> :class:`SceneInfo`, :func:`degrade`,
:func:`make_world`, :class:`World`, :class:`EventParams`,
:class:`RadiometryParams`, :class:`TerrainParams`, :class:`TextureParams`,
:class:`VisibilityParams`, :func:`visibility_window` (per-view visibility truth),
:class:`TowerParams` and :class:`Tower` (one tall flat-roofed tower).
"""

from tiledsm.synth.degrade import degrade
from tiledsm.synth.event import EventParams, PostEventWorld
from tiledsm.synth.render import RadiometryParams, render_window
from tiledsm.synth.scene import SceneInfo, make_scene
from tiledsm.synth.terrain import TerrainParams, World, make_world
from tiledsm.synth.texture import TextureParams
from tiledsm.synth.tower import Tower, TowerParams, place_tower
from tiledsm.synth.visibility import VisibilityParams, visibility_window

__all__ = [
    "make_scene",
    "SceneInfo",
    "degrade",
    "make_world",
    "World",
    "TerrainParams",
    "TextureParams",
    "RadiometryParams",
    "EventParams",
    "PostEventWorld",
    "render_window",
    "VisibilityParams",
    "visibility_window",
    "TowerParams",
    "Tower",
    "place_tower",
]
