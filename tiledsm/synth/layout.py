"""What a synthetic scene's parameters fix before anything is rendered: its
world, truth grid, height range and cameras (:func:`scene_layout`), and the
RPC fitted to a camera (:func:`fit_view`). :func:`tiledsm.synth.make_scene`
renders the scene from them; a plan reads them to size a run on a scene
not made yet.

Conventions: metres in the scene's UTM CRS; angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from tiledsm.geometry.grid import GroundGrid, utm_crs
from tiledsm.geometry.pushbroom import PushbroomCamera
from tiledsm.synth.event import EventParams, PostEventWorld
from tiledsm.synth.terrain import TerrainParams, World, make_world
from tiledsm.synth.texture import TextureParams
from tiledsm.synth.tower import TowerParams, place_tower

__all__ = ["DEFAULT_ROLLS", "SceneLayout", "scene_layout", "fit_view", "view_pitches"]

#: default roll angles of views 0, 1, 2, degrees (small, different: the
#: epipolar geometry is not trivially aligned with the image axes)
DEFAULT_ROLLS = (1.0, -0.5, 0.3)


def view_pitches(bh: float, views: int) -> tuple[float, ...]:
    """Along-track incidences (degrees) of the views for a B/H of ``bh``."""
    t = 0.5 * float(bh)
    tans = (-t, t) if views == 2 else (-t, t, 0.0)
    return tuple(math.degrees(math.atan(v)) for v in tans)


@dataclass(frozen=True)
class SceneLayout:
    """What a synthetic scene's parameters fix before anything is rendered:
    its world, truth grid, height range and cameras (see :func:`scene_layout`).

    Attributes
    ----------
    world : World
    grid : GroundGrid
        The truth grid: ``size x size`` cells of ``gsd`` metres centred on
        ``origin``, in the UTM zone of the scene centre.
    origin : (float, float)
        Easting and northing of the world's local origin (metres).
    height_range : (float, float)
        Ellipsoidal heights of the terrain (both epochs with an event) over
        the scene and a margin, metres.
    h0 : float
        Terrain height at the origin, metres.
    cameras, post_cameras : tuple of PushbroomCamera
        The pre-event views and the post-event ones (the same objects when
        the post acquisition is not another one).
    event : EventParams or None
    post_world : PostEventWorld or None
    """

    world: World
    grid: GroundGrid
    origin: tuple[float, float]
    height_range: tuple[float, float]
    h0: float
    cameras: tuple
    post_cameras: tuple
    event: EventParams | None = None
    post_world: PostEventWorld | None = None


def scene_layout(
    size: int = 1024,
    gsd: float = 0.5,
    bh: float = 0.4,
    seed: int = 0,
    views: int = 2,
    event: bool = False,
    chunk: int = 512,
    *,
    center: tuple[float, float] = (5.2, 44.2),
    azimuth_deg: float = 190.0,
    rolls_deg: tuple[float, ...] = DEFAULT_ROLLS,
    altitude: float = 700e3,
    terrain: TerrainParams | None = None,
    texture: TextureParams | None = None,
    event_params: EventParams | None = None,
    tower: TowerParams | None = None,
) -> SceneLayout:
    """The world, truth grid, height range and cameras of :func:`make_scene`
    with the same parameters, in milliseconds and without writing anything
    (e.g. to plan a run on a scene not made yet)."""
    from pyproj import Transformer

    world = make_world(seed, gsd, terrain, texture)
    crs = utm_crs(*center)
    e0, n0 = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(*center)
    origin = (float(round(e0)), float(round(n0)))
    extent = size * gsd
    grid = GroundGrid(crs, origin[0] - extent / 2, origin[1] + extent / 2, gsd, size, size, chunk)
    if tower is not None:
        world = replace(world, tower=place_tower(world, tower, grid, origin))
    ev = None
    ground_post = None
    if event:
        ev = event_params or EventParams.for_extent(extent)
        ground_post = PostEventWorld(world, ev)
    margin = 0.3 * extent + 300.0
    box = (-extent / 2 - margin, extent / 2 + margin, -extent / 2 - margin, extent / 2 + margin)
    h_range = world.height_bounds(*box)
    if ground_post is not None:
        lo, hi = ground_post.height_bounds(*box)
        h_range = (min(lo, h_range[0]), max(hi, h_range[1]))
    h0 = float(world.relief.points(0.0, 0.0) + world.terrain.base_height)
    cameras = tuple(
        PushbroomCamera(crs, origin[0], origin[1], h0, size, size, gsd, pitch_deg=p,
                        roll_deg=rolls_deg[i % len(rolls_deg)], azimuth_deg=azimuth_deg, altitude=altitude)
        for i, p in enumerate(view_pitches(bh, views))
    )
    post_cameras = cameras
    if ev is not None and (any(ev.post_aim_offset) or ev.post_bh is not None):
        # another acquisition: aimed elsewhere and/or with its own base, so its pixels and its
        # disparities sample the ground at other sub-pixel phases (own RPCs)
        ox, oy = ev.post_aim_offset
        pitches = view_pitches(ev.post_bh, views) if ev.post_bh is not None else [c.pitch_deg for c in cameras]
        post_cameras = tuple(replace(c, e0=c.e0 + ox, n0=c.n0 + oy, pitch_deg=p) for c, p in zip(cameras, pitches))
    return SceneLayout(world, grid, origin, (float(h_range[0]), float(h_range[1])), h0, cameras, post_cameras, ev,
                       ground_post)


def fit_view(camera: PushbroomCamera, h_range, view: int):
    """The RPC fitted to ``camera`` over ``h_range`` (view number ``view``;
    post-event views are ``100 + i``) and the fit's report."""
    from tiledsm.geometry.fit import fit_rpc_report

    r = np.array([0, 0, camera.rows, camera.rows] * 2, float)
    c = np.array([0, camera.cols, 0, camera.cols] * 2, float)
    h = np.repeat(np.asarray(h_range, float), 4)
    lon, lat = camera.localize(r, c, h)
    dlon = 0.02 * (lon.max() - lon.min())
    dlat = 0.02 * (lat.max() - lat.min())
    rpc, report = fit_rpc_report(
        camera.project, (lon.min() - dlon, lon.max() + dlon), (lat.min() - dlat, lat.max() + dlat),
        tuple(h_range), (camera.rows, camera.cols), source=f"synthetic pushbroom view_{view}",
    )
    return rpc, report
