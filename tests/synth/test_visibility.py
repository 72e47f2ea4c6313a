"""Visibility truth: analytic box building, renderer cross-check, tiling, files."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import rasterio
from scipy import ndimage

from tiledsm.geometry.grid import GroundGrid
from tiledsm.geometry.pushbroom import PushbroomCamera
from tiledsm.synth import VisibilityParams, render_window, visibility_window
from tiledsm.synth.visibility import edge_cells

E0, N0 = 650000.0, 4896000.0


@dataclass(frozen=True)
class BoxWorld:
    """Level ground at ``h`` with one square building (centre, half side, top)."""

    h: float = 100.0
    box: tuple = ((0.0, 0.0), 5.0, 130.0)

    def evaluate(self, x, y):
        X, Y = np.meshgrid(np.asarray(x, float), np.asarray(y, float))
        (cx, cy), half, top = self.box
        inside = (np.abs(X - cx) <= half) & (np.abs(Y - cy) <= half)
        h = np.where(inside, top, self.h).astype(np.float32)
        return h, np.full(X.shape, 0.5, np.float32), inside.astype(np.uint8)

    def height_bounds(self, *box):
        return self.h - 1.0, self.box[2] + 1.0


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(1)


def _hidden_by_box(x, y, g, world):
    """Analytic oracle: the segment ``(x, y) + u g``, ``0 < u <= top - h``,
    meets the building's footprint (slab test)."""
    (cx, cy), half, top = world.box
    lo, hi = np.zeros_like(x), np.full_like(x, top - world.h)
    for p, d, c in ((x, g[0], cx), (y, g[1], cy)):
        if abs(d) < 1e-12:
            ok = np.abs(p - c) <= half
            lo = np.where(ok, lo, np.inf)
        else:
            t1, t2 = (c - half - p) / d, (c + half - p) / d
            lo, hi = np.maximum(lo, np.minimum(t1, t2)), np.minimum(hi, np.maximum(t1, t2))
    return lo <= hi


def test_box_building_hides_the_ground_behind_it_and_not_its_roof():
    world = BoxWorld()
    cam = PushbroomCamera("EPSG:32631", E0, N0, 100.0, 128, 128, 0.5, pitch_deg=20.0, roll_deg=2.0)
    grid = GroundGrid("EPSG:32631", E0 - 32, N0 + 32, 0.5, 128, 128, 64)
    vis, edge = visibility_window(world, [cam], (E0, N0), world.height_bounds(), grid, (0, 128), (0, 128))
    vis = vis[0]
    X, Y = np.meshgrid(grid.x - E0, grid.y - N0)
    g = cam.parallax()  # horizontal run per metre of rise, towards the satellite
    (cx, cy), half, top = world.box
    roof = (np.abs(X - cx) <= half) & (np.abs(Y - cy) <= half)
    row, col = cam.project_xy(X + E0, Y + N0, np.where(roof, top, world.h))
    inside = (row >= 0) & (row < 128) & (col >= 0) & (col < 128)
    oracle = inside & (roof | ~_hidden_by_box(X, Y, g, world))
    # compare away from the oracle's boundaries (one cell) and the roof border
    sure = ~(ndimage.binary_dilation(oracle, iterations=1) ^ ndimage.binary_erosion(oracle, iterations=1))
    sure &= ~edge
    assert sure.sum() > 0.9 * vis.size
    assert (vis == oracle)[sure].all()
    # the shadow is where expected: the ground just behind the building, away from the sensor, is hidden
    behind = ~roof & (np.abs(X - cx + 20 * g[0]) <= half - 1) & (np.abs(Y - cy + 20 * g[1]) <= half - 1)
    assert behind.sum() > 100 and not vis[behind].any()
    assert vis[roof & ~edge].all() and roof[~edge].sum() > 300
    # hidden share = shadow area / grid area, shadow = footprint swept by (top - h) g
    L = (top - world.h) * np.abs(g)
    shadow = (2 * half) * (L[0] + L[1]) + L[0] * L[1]
    assert abs((inside & ~vis & ~roof).sum() * 0.25 - shadow) < 0.1 * shadow
    # the edge cells are the ring around the walls, two cells wide
    sq = np.ones((3, 3), bool)
    ring = ndimage.binary_dilation(roof, sq) & ~ndimage.binary_erosion(roof, sq)
    np.testing.assert_array_equal(edge, ring)


def test_flat_ground_is_visible_everywhere_inside_the_image():
    world = BoxWorld(box=((500.0, 500.0), 1.0, 100.0))  # no building in view
    cam = PushbroomCamera("EPSG:32631", E0, N0, 100.0, 64, 64, 0.5, pitch_deg=-25.0, roll_deg=4.0)
    grid = GroundGrid("EPSG:32631", E0 - 20, N0 + 20, 0.5, 80, 80, 80)
    vis, edge = visibility_window(world, [cam], (E0, N0), (99.0, 101.0), grid, (0, 80), (0, 80))
    X, Y = np.meshgrid(grid.x, grid.y)
    row, col = cam.project_xy(X, Y, 100.0)
    inside = (row >= 0) & (row < 64) & (col >= 0) & (col < 64)
    assert 0.3 < inside.mean() < 0.9  # the grid overhangs the image: the bounds test has power
    np.testing.assert_array_equal(vis[0], inside)
    assert not edge.any()


def test_edge_cells_threshold():
    h = np.zeros((6, 7))
    h[:, 4:] = 2.0  # a 2 m step between columns 3 and 4
    e = edge_cells(h, 1.5)
    assert e.shape == (4, 5)
    assert e[:, 2:4].all() and not e[:, :2].any() and not e[:, 4:].any()
    assert not edge_cells(h, 2.5).any()
    with pytest.raises(Exception, match="edge_range"):
        VisibilityParams(edge_range=0.0)


def test_scene_masks_match_untiled_evaluation(small_scene):
    """The 64-cell tiled files equal one call on the whole grid."""
    s = small_scene
    vis, edge = visibility_window(s.world, s.cameras, s.origin, s.height_range, s.grid, (0, 192), (0, 192))
    for i, p in enumerate(s.visible_views):
        np.testing.assert_array_equal(_read(p), vis[i])
    np.testing.assert_array_equal(_read(s.edge_mask), edge)
    allv = _read(s.visible_mask)
    np.testing.assert_array_equal(allv, vis.all(axis=0) & ~edge)
    assert 0.75 < allv.mean() < 0.97  # measured 0.884 (3 views, seed 3)
    assert 0.85 < min(_read(p).mean() for p in s.visible_views)


def test_visible_cells_are_what_the_renderer_sees(small_scene):
    """Independent oracle: the renderer's hit point at the cell's projection
    (bilinear in the truth hit image) lies within one GSD of the cell."""
    s = small_scene
    cam = s.cameras[0]
    _, _, xyz = render_window(s.world, cam, s.origin, s.height_range, (0, 192), (0, 192), truth=True)
    X, Y = np.meshgrid(s.grid.x - s.origin[0], s.grid.y - s.origin[1])
    H = _read(s.truth_dsm).astype(float)
    row, col = cam.project_xy(X + s.origin[0], Y + s.origin[1], H)
    inside = (row >= 0) & (row < 192) & (col >= 0) & (col < 192)
    hit = np.stack([ndimage.map_coordinates(xyz[..., k], [row - 0.5, col - 0.5], order=1, mode="nearest")
                    for k in range(3)], -1)
    oracle = inside & (np.linalg.norm(hit - np.stack([X, Y, H], -1), axis=-1) < 0.5)
    vis = _read(s.visible_views[0]).astype(bool)
    ok = ~_read(s.edge_mask).astype(bool)
    assert (oracle != vis)[ok].mean() < 0.01
    assert (~oracle & inside).sum() > 200  # there is occlusion to find


def test_scene_json_and_post_event_masks(small_scene):
    s = small_scene
    doc = json.loads(s.scene_json.read_text())
    t = doc["truth"]
    assert t["visible_mask"] == "visible.tif" and t["edge_mask"] == "edge.tif"
    assert t["visible_views"] == ["visible_0.tif", "visible_1.tif", "visible_2.tif"]
    assert t["visibility"]["edge_range"] == VisibilityParams().edge_range
    ev = s.event
    assert doc["event"]["post_visible"] == "post_visible.tif"
    with rasterio.open(ev["post_visible"]) as ds:
        assert ds.dtypes[0] == "uint8" and ds.crs.to_epsg() == 32631 and ds.transform == s.grid.transform
        post = ds.read(1)
    post_views = np.stack([_read(p) for p in ev["post_visible_views"]])
    np.testing.assert_array_equal(post, post_views.all(axis=0) & ~_read(ev["post_edge"]).astype(bool))
    assert 0.75 < post.mean() < 0.97
    # the fault scarp (throw 2 m > edge_range) is an edge after the event only
    assert _read(ev["post_edge"]).sum() > _read(s.edge_mask).sum()
