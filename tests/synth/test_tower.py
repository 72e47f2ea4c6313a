"""The optional tall tower: truth footprint and roof, visibility and
occlusion, and the rendered views checked through the files' RPCs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from scipy import ndimage

from tiledsm.errors import TiledsmError
from tiledsm.geometry import RPC
from tiledsm.synth import RadiometryParams, TowerParams, make_scene, make_world, place_tower
from tiledsm.synth.scene import measured_parallax

SIZE, GSD, SEED = 256, 0.5, 0
TOWER = TowerParams(height_m=65.0, side_m=16.0)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The same 256 x 256 scene with the default tower at its centre (which
    straddles the 128-cell tiles) and without it."""
    kw = dict(size=SIZE, gsd=GSD, bh=0.4, seed=SEED, views=2, chunk=128, workers=2)
    with_tower = make_scene(tmp_path_factory.mktemp("tower"), tower=TOWER, **kw)
    without = make_scene(tmp_path_factory.mktemp("no_tower"), **kw)
    return with_tower, without


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(1)


def _rpc(path):
    with rasterio.open(path) as ds:
        return RPC.from_gdal(ds.rpcs.to_gdal())


def _interior(window, shape, erode=2):
    r0, r1, c0, c1 = window
    m = np.zeros(shape, bool)
    m[r0 + erode:r1 - erode, c0 + erode:c1 - erode] = True
    return m


def test_truth_has_the_roof_at_the_stated_height_over_exactly_the_footprint(pair):
    scene, ref = pair
    tw = scene.tower
    r0, r1, c0, c1 = scene.tower_window
    assert ref.tower is None and ref.tower_window is None
    # 16 m side = 32 cells, centred on the scene centre
    assert (r1 - r0, c1 - c0) == (32, 32) and (r0 + r1, c0 + c1) == (SIZE, SIZE)
    dsm, dsm_ref = _read(scene.truth_dsm), _read(ref.truth_dsm)
    lab = _read(scene.truth_label)
    roof = np.zeros(dsm.shape, bool)
    roof[r0:r1, c0:c1] = True
    # flat roof at max(ground under the footprint) + height, exactly on the window
    assert np.all(dsm[roof] == np.float32(tw.roof_height)) and np.all(lab[roof] == 1)
    x0, x1, y0, y1 = tw.footprint
    xs, ys = np.linspace(x0, x1, 65), np.linspace(y0, y1, 65)
    ground = scene.world.relief.grid(xs, ys, dtype=np.float64) + scene.world.terrain.base_height
    assert abs(tw.roof_height - (ground.max() + TOWER.height_m)) < 0.01
    assert 60.0 < tw.roof_height - dsm_ref[roof].max()  # well above whatever stood there
    # nothing else changed: outside the window the truth is the tower-free one, bit for bit
    np.testing.assert_array_equal(dsm[~roof], dsm_ref[~roof])
    np.testing.assert_array_equal(lab[~roof], _read(ref.truth_label)[~roof])
    # area under 1 % of a 384-pixel scene at 0.5 m
    assert (TOWER.side_m / (384 * GSD)) ** 2 < 0.01
    doc = json.loads(scene.scene_json.read_text())
    assert doc["tower"]["window_rows_cols"] == [r0, r1, c0, c1]
    assert doc["tower"]["roof_height_m"] == tw.roof_height
    assert "tower" not in json.loads(ref.scene_json.read_text())


def test_roof_is_visible_in_every_view_and_not_an_edge(pair):
    scene, _ = pair
    inner = _interior(scene.tower_window, (SIZE, SIZE))
    for p in scene.visible_views + (scene.visible_mask,):
        assert _read(p)[inner].all(), p.name
    assert not _read(scene.edge_mask)[inner].any()
    # the walls are edges: the cells just outside the footprint
    r0, r1, c0, c1 = scene.tower_window
    edge = _read(scene.edge_mask)
    assert edge[r0 - 1, c0:c1].all() and edge[r1, c0:c1].all() and edge[r0:r1, c0 - 1].all()


def _shadow_oracle(dsm, grid, origin, tower, g):
    """Cells whose segment ``(x, y, h) + u (g, 1)``, ``0 < u <= roof - h``,
    crosses the footprint (slab test): the ground the tower hides."""
    X, Y = np.meshgrid(grid.x - origin[0], grid.y - origin[1])
    x0, x1, y0, y1 = tower.footprint
    lo, hi = np.zeros(X.shape), tower.roof_height - dsm.astype(float)
    for p, d, a, b in ((X, g[0], x0, x1), (Y, g[1], y0, y1)):
        t1, t2 = (a - p) / d, (b - p) / d
        lo, hi = np.maximum(lo, np.minimum(t1, t2)), np.minimum(hi, np.maximum(t1, t2))
    return lo <= hi


def test_walls_hide_the_ground_behind_the_tower(pair):
    """The cells a view loses to the tower are those whose line of sight
    (from the file's RPC) crosses the tower: the analytic shadow."""
    scene, ref = pair
    dsm_ref = _read(ref.truth_dsm)
    outside = ~_interior(scene.tower_window, (SIZE, SIZE), erode=0)
    outside &= ndimage.binary_erosion(outside, iterations=2)  # leave the wall cells out
    r0, r1, c0, c1 = scene.tower_window
    fx, fy = scene.grid.x[(c0 + c1) // 2], scene.grid.y[(r0 + r1) // 2]
    to_ll = Transformer.from_crs(scene.grid.crs, "EPSG:4326", always_xy=True)
    for pv, pv_ref, pimg in zip(scene.visible_views, ref.visible_views, scene.views):
        rpc = _rpc(pimg)
        row, col = rpc.project(*to_ll.transform(fx, fy), float(dsm_ref[r0, c0]))
        g = measured_parallax(rpc, scene.grid.crs, float(row), float(col), float(dsm_ref[r0, c0]))
        was = _read(pv_ref).astype(bool) & outside
        lost = was & ~_read(pv).astype(bool)
        oracle = _shadow_oracle(dsm_ref, scene.grid, scene.origin, scene.tower, g) & was
        expected_area = TOWER.side_m * (TOWER.height_m) * (abs(g[0]) + abs(g[1]))
        assert oracle.sum() * GSD**2 > 0.7 * expected_area  # a real shadow, mostly in the scene
        # the lost cells are the oracle's, up to a band along the shadow's outline
        band = ndimage.binary_dilation(oracle) & ~ndimage.binary_erosion(oracle)
        assert (lost & ~oracle & ~band).sum() == 0
        assert (oracle & ~lost & ~band).sum() == 0
        assert abs(int(lost.sum()) - int(oracle.sum())) < 0.05 * oracle.sum()


def _roof_pixels(rpc, tower, origin, crs, shape, erode=2):
    """Pixels inside the projection of the roof outline (file RPC), eroded."""
    x0, x1, y0, y1 = tower.footprint
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(
        np.array([x0, x1, x1, x0]) + origin[0], np.array([y0, y0, y1, y1]) + origin[1])
    r, c = rpc.project(lon, lat, np.full(4, tower.roof_height))
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]] + 0.5
    inside = np.ones(shape, bool)
    for k in range(4):
        (ra, ca), (rb, cb) = (r[k], c[k]), (r[(k + 1) % 4], c[(k + 1) % 4])
        side = lambda R, C: (rb - ra) * (C - ca) - (cb - ca) * (R - ra)  # noqa: E731
        inside &= side(rr, cc) * side(r.mean(), c.mean()) > 0
    return ndimage.binary_erosion(inside, iterations=erode), r


def test_views_show_the_textured_roof_where_the_rpc_puts_it(pair):
    """Inside the roof's projection (file RPC), each image is the roof texture
    ``roof_albedo (1 + 0.3 T(x, y))`` at the points the RPC localises at the
    roof height; not at 2 m off it, and not in the tower-free images."""
    scene, ref = pair
    tw, (e0, n0) = scene.tower, scene.origin
    to_en = Transformer.from_crs("EPSG:4326", scene.grid.crs, always_xy=True)
    rad = RadiometryParams()
    shade = rad.ambient + (1 - rad.ambient) * rad.sun[2]
    rows = []
    for p, p_ref in zip(scene.views, ref.views):
        rpc = _rpc(p)
        img, img_ref = _read(p).astype(float), _read(p_ref).astype(float)
        m, corner_rows = _roof_pixels(rpc, tw, scene.origin, scene.grid.crs, img.shape)
        rows.append(corner_rows.mean())
        assert m.sum() > 0.6 * (TOWER.side_m / GSD) ** 2
        i, j = np.nonzero(m)

        def predicted(dh):
            x, y = to_en.transform(*rpc.localize(i + 0.5, j + 0.5, np.full(i.size, tw.roof_height + dh)))
            return TOWER.roof_albedo * (1 + 0.3 * scene.world.albedo_field.points(x - e0, y - n0))

        pred = predicted(0.0)
        assert np.corrcoef(pred, img[m])[0, 1] > 0.97
        assert abs(img[m].mean() - (rad.offset + rad.gain * shade * pred.mean())) < 5, img[m].mean()  # DN
        for dh in (-2.0, 2.0):
            assert np.corrcoef(predicted(dh), img[m])[0, 1] < 0.93
        assert np.corrcoef(pred, img_ref[m])[0, 1] < 0.6
    # the roof moves between the views by ~ height * B/H / gsd pixels (here along the rows)
    shift = abs(rows[1] - rows[0])
    assert 0.8 * TOWER.height_m * scene.bh / GSD < shift < 1.25 * TOWER.height_m * scene.bh / GSD


def test_default_scene_has_no_tower():
    world = make_world(SEED, GSD)
    assert world.tower is None
    x = np.linspace(-20, 20, 41)
    h, a, lab = world.evaluate(x, x)
    assert h.max() < world.height_bounds(-20, 20, -20, 20)[1]


def test_tower_params_are_checked(tmp_path):
    with pytest.raises(TiledsmError):
        TowerParams(height_m=-1.0)
    with pytest.raises(TiledsmError):
        TowerParams(side_m=0.0)
    from tiledsm.geometry.grid import GroundGrid

    grid = GroundGrid("EPSG:32631", 0.0, 64.0, 0.5, 128, 128)
    world = make_world(SEED, GSD)
    with pytest.raises(TiledsmError, match="does not fit"):
        place_tower(world, TowerParams(offset_m=(30.0, 0.0)), grid, (32.0, 32.0))
    tw = place_tower(world, TowerParams(side_m=5.2, offset_m=(3.1, -4.0)), grid, (32.0, 32.0))
    r0, r1, c0, c1 = tw.window
    assert r1 - r0 == c1 - c0 == 10  # 5.2 m -> 10 cells of 0.5 m
    x0, x1, y0, y1 = tw.footprint
    assert abs(0.5 * (x0 + x1) - 3.1) <= 0.25 and abs(0.5 * (y0 + y1) + 4.0) <= 0.25
    assert x0 == -32.0 + c0 * 0.5 and y1 == 32.0 - r0 * 0.5  # on cell edges


def test_clearance_removes_objects_around_the_tower():
    from dataclasses import replace

    from tiledsm.geometry.grid import GroundGrid

    grid = GroundGrid("EPSG:32631", -96.0, 96.0, 0.5, 384, 384)
    world = make_world(SEED, GSD)
    base = world.evaluate(grid.x, grid.y)
    for clear in (0.0, 6.0):
        # in a built-up, wooded corner of the seed-0 world
        tw = place_tower(world, TowerParams(offset_m=(-40.0, 40.0), clearance_m=clear), grid, (0.0, 0.0))
        w = replace(world, tower=tw)
        xs = grid.x[tw.window[2] - 14:tw.window[3] + 14]
        ys = grid.y[tw.window[0] - 14:tw.window[1] + 14]
        h, _, lab = w.evaluate(xs, ys)
        ring = np.ones(h.shape, bool)
        ring[14:-14, 14:-14] = False  # 7 m around the footprint
        near = ring.copy()
        near[:2], near[-2:], near[:, :2], near[:, -2:] = False, False, False, False  # within 6 m
        assert (lab[14:-14, 14:-14] == 1).all()
        if not clear:
            assert (lab[near] != 0).sum() > 100  # objects next to the tower: the check below has power
        else:
            assert (lab[near] == 0).all()
            bare = world.relief.grid(xs, ys) + np.float32(world.terrain.base_height)
            np.testing.assert_allclose(h[near], bare[near], atol=1e-3)
        # beyond the cleared ring nothing changes
        r0, c0 = tw.window[0] - 14, tw.window[2] - 14
        far = ~ndimage.binary_dilation(~ring, np.ones((3, 3)), iterations=12)  # centres >= 6.25 m away
        np.testing.assert_array_equal(lab[far], base[2][r0:r0 + lab.shape[0], c0:c0 + lab.shape[1]][far])


def test_cli_tower_flag(tmp_path, capsys):
    from tiledsm.cli import main

    out = tmp_path / "s"
    assert main(["synth", str(out), "--size", "96", "--tower", "40", "--tower-side", "8", "--chunk", "96",
                 "--workers", "1", "--json"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    r0, r1, c0, c1 = doc["tower"]["window_rows_cols"]
    assert (r1 - r0, c1 - c0) == (16, 16)
    dsm = _read(out / "truth_dsm.tif")
    assert np.all(dsm[r0:r1, c0:c1] == np.float32(doc["tower"]["roof_height_m"]))
    assert json.loads(capsys.readouterr().out)["tower"]["window_rows_cols"] == [r0, r1, c0, c1]
