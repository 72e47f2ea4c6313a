"""make_scene outputs: files, RPCs, B/H, truth DSM, event truth, tiling."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from tiledsm.geometry import RPC


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(1), ds.rpcs, ds.crs, ds.transform


def test_views_are_uint16_with_rpc_and_no_crs(small_scene):
    for p in small_scene.views + small_scene.event["post_views"]:
        img, rpcs, crs, _ = _read(p)
        assert img.dtype == np.uint16 and img.shape == (192, 192)
        assert crs is None and rpcs is not None
        assert 0 <= img.min() and img.max() <= 4095 and img.std() > 100
    _, _, crs, transform = _read(small_scene.truth_dsm)
    assert crs.to_epsg() == 32631 and transform.a == 0.5
    doc = json.loads(small_scene.scene_json.read_text())
    assert doc["crs"] == "EPSG:32631" and len(doc["views"]) == 3 and doc["bh_measured"] == small_scene.bh


def test_bh_measured_from_file_rpcs_is_the_asked_one(small_scene):
    from pyproj import Transformer

    rpcs = [RPC.from_gdal(_read(p)[1].to_gdal()) for p in small_scene.views]
    tr = Transformer.from_crs("EPSG:4326", small_scene.grid.crs, always_xy=True)
    par = []
    for rpc in rpcs:
        lon, lat = rpc.localize(np.array([96.0, 96.0]), np.array([96.0, 96.0]), np.array([300.0, 400.0]))
        x, y = tr.transform(lon, lat)
        par.append(np.array([x[1] - x[0], y[1] - y[0]]) / 100.0)
    assert abs(np.linalg.norm(par[0] - par[1]) - 0.4) < 0.04
    assert abs(np.linalg.norm(par[0] - par[2]) - 0.2) < 0.02
    assert abs(small_scene.bh - 0.4) < 0.04


def test_file_rpc_projects_truth_points_like_the_pushbroom(small_scene):
    from pyproj import Transformer

    dsm, _, _, transform = _read(small_scene.truth_dsm)
    rng = np.random.default_rng(0)
    i = rng.integers(0, 192, 300)
    j = rng.integers(0, 192, 300)
    x, y = transform @ (j + 0.5, i + 0.5)
    h = dsm[i, j].astype(float)
    lon, lat = Transformer.from_crs(small_scene.grid.crs, "EPSG:4326", always_xy=True).transform(x, y)
    for p, cam in zip(small_scene.views, small_scene.cameras):
        rpc = RPC.from_gdal(_read(p)[1].to_gdal())
        r1, c1 = rpc.project(lon, lat, h)
        r2, c2 = cam.project_xy(x, y, h)
        assert np.hypot(r1 - r2, c1 - c2).max() < 0.05
    assert max(small_scene.fit_residual_px) < 0.05


def test_truth_dsm_equals_direct_evaluation(small_scene):
    """The 64-cell tiled truth equals one evaluation of the whole grid."""
    dsm, _, _, _ = _read(small_scene.truth_dsm)
    lab, _, _, _ = _read(small_scene.truth_label)
    g, (e0, n0) = small_scene.grid, small_scene.origin
    h, _, l = small_scene.world.evaluate(g.x - e0, g.y - n0)
    np.testing.assert_allclose(dsm, h, atol=2e-3)
    assert (lab != l).mean() < 1e-3
    assert len(np.unique(lab)) >= 2


def test_views_see_the_truth_surface(small_scene):
    """A rendered pixel and the truth DSM agree: the view's image of the
    scene, re-rendered at a pixel, hits the DSM height at the hit position."""
    from tiledsm.synth import render_window
    from tiledsm.synth.render import RadiometryParams

    cam = small_scene.cameras[0]
    dn, rad, xyz = render_window(small_scene.world, cam, small_scene.origin, small_scene.height_range,
                                 (64, 96), (64, 96), RadiometryParams(), seed=3, view=0, truth=True)
    img, _, _, _ = _read(small_scene.views[0])
    assert np.abs(img[64:96, 64:96].astype(int) - dn).max() <= 1
    h, _, _ = small_scene.world.evaluate(np.array([0.0]), np.array([0.0]))
    hit = xyz.reshape(-1, 3)
    grid_h = [small_scene.world.evaluate(np.array([p[0]]), np.array([p[1]]))[0][0, 0] for p in hit[::37]]
    err = np.abs(np.array(grid_h) - hit[::37, 2])
    assert np.median(err) < 0.05


def test_event_truth(small_scene):
    ev = small_scene.event
    pre, _, _, _ = _read(small_scene.truth_dsm)
    post, _, _, _ = _read(ev["post_dsm"])
    dh, _, _, _ = _read(ev["dh"])
    dx, _, _, _ = _read(ev["dx"])
    dy, _, _, _ = _read(ev["dy"])
    dz, _, _, _ = _read(ev["dz"])
    lab, _, _, _ = _read(small_scene.truth_label)
    np.testing.assert_allclose(dh, post - pre, atol=1e-5)
    p = ev["params"]
    # horizontal slip: +-slip/2 along the strike on each block
    s = np.hypot(dx, dy)
    np.testing.assert_allclose(s, p.slip / 2, atol=1e-6)
    assert (dx > 0).any() and (dx < 0).any()  # the fault crosses the scene
    # vertical: throw/2 on each side plus a positive uplift
    assert dz.max() - dz.min() > p.throw * 0.9
    # on bare, gently sloping ground dh = dz - grad(f) . (dx, dy) to first order
    gy, gx = np.gradient(pre.astype(float), -0.5, 0.5)
    ground = (lab == 0) & (np.hypot(gx, gy) < 0.5)
    from scipy import ndimage

    ground &= ndimage.binary_erosion(ground, iterations=3)
    ground &= ndimage.binary_erosion(dx > 0, iterations=4) | ndimage.binary_erosion(dx < 0, iterations=4)
    pred = dz - gx * dx - gy * dy
    assert ground.sum() > 1000
    err = np.median(np.abs(dh - pred)[ground])
    assert err < 0.05
    assert np.median(np.abs(dh - dz)[ground]) > 2 * err  # the slope term matters: the check has power
