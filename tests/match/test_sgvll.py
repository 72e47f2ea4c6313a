"""SGVLL object-space matching on a synthetic scene with analytic affine RPCs
(truth known exactly; see conftest.py)."""

import numpy as np
import pytest

from tiledsm.errors import MatchingError
from tiledsm.match.sgvll import (
    SGVLLParams,
    bounds_from_coarse,
    downsample,
    height_step,
    match_block,
    match_pyramid,
    scale_rpc,
)

from match_synthetic import CRS, make_scene, scene_grid


def _stats(h, truth):
    e = (h - truth)[np.isfinite(h)]
    nmad = 1.4826 * np.median(np.abs(e - np.median(e)))
    return nmad, np.isfinite(h).mean(), np.median(e)


@pytest.fixture(scope="module")
def grid(synthetic_scene):
    gx, gy = scene_grid(synthetic_scene)
    X, Y = np.meshgrid(gx, gy)
    return gx, gy, synthetic_scene.height(X, Y)


def test_height_step_from_parallax(synthetic_scene):
    # tilts +-0.4 px/m: 0.8 px of parallax per metre
    step = height_step(synthetic_scene.rpcs, 3.0, 43.0, 100.0, SGVLLParams(step_px=0.5))
    assert step == pytest.approx(0.5 / 0.8, rel=1e-9)


def test_match_block_recovers_terrain(synthetic_scene, grid):
    gx, gy, truth = grid
    d = {}
    h, conf = match_block(synthetic_scene.images, synthetic_scene.rpcs, None, gx, gy, CRS, 85.0, 125.0, details=d)
    nmad, compl, med = _stats(h, truth)
    # measured: NMAD 0.10 m, completeness 94.6 %, median error < 0.01 m
    assert nmad < 0.2 and compl > 0.9 and abs(med) < 0.05
    assert np.nanmean(conf[np.isfinite(h)]) > 0.8
    assert d["n_candidates"] == 65 and d["step"] == pytest.approx(0.625)


def test_match_block_surface_following_band(synthetic_scene, grid):
    """Per-cell ranges around a (here: true) surface: windows follow it."""
    gx, gy, truth = grid
    h, _ = match_block(synthetic_scene.images, synthetic_scene.rpcs, None, gx, gy, CRS, truth - 3, truth + 3)
    nmad, compl, med = _stats(h, truth)
    assert nmad < 0.06 and compl > 0.9  # measured 0.03 m


def test_match_pyramid(synthetic_scene, grid):
    gx, gy, truth = grid
    d = {}
    h, _ = match_pyramid(synthetic_scene.images, synthetic_scene.rpcs, None, gx, gy, CRS, 85.0, 125.0, details=d)
    nmad, compl, med = _stats(h, truth)
    assert nmad < 0.2 and compl > 0.9  # measured 0.10 m, 95 %
    assert [lv["factor"] for lv in d["levels"]] == [4, 2, 1]
    assert d["levels"][-1]["n_candidates"] < 40


def test_windows_offsets_equal_full_images(synthetic_scene, grid):
    gx, gy, _ = grid
    gx, gy = gx[40:90], gy[50:100]
    sc = synthetic_scene
    ref, _ = match_block(sc.images, sc.rpcs, None, gx, gy, CRS, 90.0, 120.0)
    wins = [(30, 35), (25, 60)]
    crops = [im[r:, c:] for im, (r, c) in zip(sc.images, wins)]
    got, _ = match_block(crops, sc.rpcs, wins, gx, gy, CRS, 90.0, 120.0)
    assert np.array_equal(np.isnan(ref), np.isnan(got))
    assert np.nanmax(np.abs(ref - got)) < 1e-4


def test_block_interior_agrees_with_whole(synthetic_scene, grid):
    """A block with a 32-cell halo reproduces the whole-grid result in its interior."""
    gx, gy, _ = grid
    sc = synthetic_scene
    whole, _ = match_block(sc.images, sc.rpcs, None, gx, gy, CRS, 85.0, 125.0)
    r0, r1, c0, c1 = 20, 130, 30, 150
    part, _ = match_block(sc.images, sc.rpcs, None, gx[c0:c1], gy[r0:r1], CRS, 85.0, 125.0)
    a = whole[r0 + 32 : r1 - 32, c0 + 32 : c1 - 32]
    b = part[32:-32, 32:-32]
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.9
    assert np.median(np.abs(a - b)[both]) < 1e-3


def test_three_views(grid):
    sc = make_scene(tilts=(0.4, 0.0, -0.4), seed=1)
    gx, gy, _ = grid
    X, Y = np.meshgrid(gx, gy)
    truth = sc.height(X, Y)
    h, _ = match_block(sc.images, sc.rpcs, None, gx, gy, CRS, 85.0, 125.0)
    nmad, compl, _ = _stats(h, truth)
    assert nmad < 0.2 and compl > 0.9


def test_bad_inputs_give_nan_or_clear_errors(synthetic_scene, grid):
    gx, gy, _ = grid
    sc = synthetic_scene
    nan_imgs = [np.full_like(im, np.nan) for im in sc.images]
    h, c = match_block(nan_imgs, sc.rpcs, None, gx[:20], gy[:20], CRS, 90.0, 110.0)
    assert np.isnan(h).all()
    # ground far outside the images
    h, c = match_block(sc.images, sc.rpcs, None, gx[:20] + 5000, gy[:20], CRS, 90.0, 110.0)
    assert np.isnan(h).all()
    # empty height range
    h, _ = match_block(sc.images, sc.rpcs, None, gx[:20], gy[:20], CRS, 110.0, 90.0)
    assert np.isnan(h).all()
    with pytest.raises(MatchingError, match="RPC"):
        match_block(sc.images[:1], sc.rpcs, None, gx, gy, CRS, 90.0, 110.0)
    with pytest.raises(MatchingError, match="max_candidates"):
        match_block(sc.images, sc.rpcs, None, gx, gy, CRS, -1000.0, 5000.0)
    with pytest.raises(MatchingError, match="parallax"):
        height_step([sc.rpcs[0], sc.rpcs[0]], 3.0, 43.0, 100.0)


def test_downsample_and_scaled_rpc_consistent(synthetic_scene):
    sc = synthetic_scene
    img, rpc = sc.images[0], sc.rpcs[0]
    small = downsample(img, 2)
    rs = scale_rpc(rpc, 0.5)
    lon, lat = rpc.localize(np.array([50.0, 80.2]), np.array([60.0, 101.7]), 100.0)
    r, c = rpc.project(lon, lat, 100.0)
    r2, c2 = rs.project(lon, lat, 100.0)
    assert np.allclose(r2, r / 2) and np.allclose(c2, c / 2)
    assert small.shape == (img.shape[0] // 2, img.shape[1] // 2)
    assert small[10, 10] == pytest.approx(img[20:22, 20:22].mean(), rel=1e-5)


def test_bounds_from_coarse():
    coarse = np.array([[10.0, 12.0], [np.nan, 20.0]], np.float32)
    lo, hi = bounds_from_coarse(coarse, 2, (4, 4), 1.0, 0.0, 100.0, radius=0, hole_radius=1)
    assert lo[0, 0] == 9.0 and hi[0, 0] == 11.0 and lo[3, 3] == 19.0
    # the hole takes the min/max of its neighbourhood, widened by 2 * margin
    assert lo[3, 0] == 8.0 and hi[3, 0] == 22.0
