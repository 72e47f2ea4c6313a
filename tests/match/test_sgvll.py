"""SGVLL object-space matching on a synthetic scene with analytic affine RPCs
(truth known exactly; see conftest.py)."""

import numpy as np
import pytest

from tiledsm.errors import MatchingError
from tiledsm.match.pyramid import SearchParams, downsample, search_from_coarse, search_halo
from tiledsm.match.sgvll import SGVLLParams, height_step, match_block

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
    """A block that knows its place in the grid, with a halo of
    ``path_period`` cells, reproduces the whole-grid result bit for bit."""
    gx, gy, _ = grid
    sc = synthetic_scene
    params = SGVLLParams()
    d = {}
    whole, wconf = match_block(sc.images, sc.rpcs, None, gx, gy, CRS, 85.0, 125.0, params, details=d)
    halo = params.path_period
    r0, r1, c0, c1 = 3, 166, 27, 161  # cut on every side, 163 x 134 cells
    part, pconf = match_block(
        sc.images, sc.rpcs, None, gx[c0:c1], gy[r0:r1], CRS, 85.0, 125.0, params, step=d["step"], origin=(r0, c0),
        axes=(gx[0], gy[0], gx[1] - gx[0], gy[1] - gy[0]),
    )
    a = whole[r0 + halo : r1 - halo, c0 + halo : c1 - halo]
    b = part[halo:-halo, halo:-halo]
    assert a.size > 0 and np.isfinite(a).mean() > 0.9
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(wconf[r0 + halo : r1 - halo, c0 + halo : c1 - halo], pconf[halo:-halo, halo:-halo])
    # without its place in the grid (own lattices), the block is close but not exact
    alone, _ = match_block(sc.images, sc.rpcs, None, gx[c0:c1], gy[r0:r1], CRS, 85.0, 125.0, params)
    assert not np.array_equal(alone[halo:-halo, halo:-halo], b, equal_nan=True)


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
    rs = rpc.scaled(0.5)
    lon, lat = rpc.localize(np.array([50.0, 80.2]), np.array([60.0, 101.7]), 100.0)
    r, c = rpc.project(lon, lat, 100.0)
    r2, c2 = rs.project(lon, lat, 100.0)
    assert np.allclose(r2, r / 2) and np.allclose(c2, c / 2)
    assert small.shape == (img.shape[0] // 2, img.shape[1] // 2)
    assert small[10, 10] == pytest.approx(img[20:22, 20:22].mean(), rel=1e-5)
    # a window read at an even offset decimates to exactly the same pixels
    part = downsample(img[6:, 10:], 2)
    np.testing.assert_array_equal(part, small[3 : 3 + part.shape[0], 5 : 5 + part.shape[1]])


def _search_whole(coarse, depth, margin, h_range, params):
    padded = np.pad(coarse, depth, constant_values=np.nan)
    return search_from_coarse(padded, depth, margin, h_range, params)


def test_search_from_coarse_values():
    """Constant coarse heights give that surface and a band of +-margin;
    under a hole the band is hole_factor times wider; beyond the fill
    radius nothing is searched."""
    p = SearchParams()
    d = search_halo(p)
    coarse = np.full((40, 40), 50.0)
    coarse[10, 10] = np.nan
    coarse[25:, 25:] = np.nan  # a big hole: its far corner is beyond the fill support
    href, lo, hi = _search_whole(coarse, d, 2.0, (0.0, 100.0), p)
    assert href.shape == (80, 80)
    assert href[4, 4] == pytest.approx(50.0) and lo[4, 4] == pytest.approx(48.0) and hi[4, 4] == pytest.approx(52.0)
    wide = p.hole_factor * 2.0
    assert lo[21, 21] == pytest.approx(50.0 - wide) and hi[21, 21] == pytest.approx(50.0 + wide)  # coarse cell (10, 10)
    assert p.hole_factor > 1  # so the hole's band really is wider
    assert np.isnan(href[79, 79]) and np.isnan(lo[79, 79])
    # a slope is reproduced by the bilinear interpolation away from holes
    ramp = np.add.outer(np.arange(40.0), np.zeros(40))
    href, _, _ = _search_whole(ramp, d, 1.0, (-10.0, 100.0), p)
    assert href[40, 7] == pytest.approx((40 + 0.5) / 2 - 0.5, abs=1e-4)


def test_search_from_coarse_blocks_equal_whole():
    """Any block with a halo of search_halo cells gives the whole-array
    result on its core, bit for bit (what makes the DSM chunk-invariant)."""
    rng = np.random.default_rng(0)
    coarse = 100 + np.cumsum(rng.normal(size=(60, 70)), axis=1)
    coarse[rng.random(coarse.shape) < 0.15] = np.nan
    coarse[20:35, 30:50] = np.nan
    p = SearchParams()
    d = search_halo(p)
    whole = _search_whole(coarse, d, 1.5, (80.0, 130.0), p)
    padded = np.pad(coarse, d, constant_values=np.nan)
    for r0, r1, c0, c1 in [(0, 17, 0, 23), (17, 60, 23, 41), (5, 38, 41, 70)]:
        block = padded[r0 : r1 + 2 * d, c0 : c1 + 2 * d]
        got = search_from_coarse(block, d, 1.5, (80.0, 130.0), p)
        np.testing.assert_array_equal(got, whole[:, 2 * r0 : 2 * r1, 2 * c0 : 2 * c1])
    with pytest.raises(MatchingError, match="halo"):
        search_from_coarse(padded, d - 1, 1.5, (80.0, 130.0), p)


@pytest.mark.parametrize("holes", ["none", "scattered", "one big", "at the edges", "halo only", "all"])
def test_search_from_coarse_fills_holes_as_the_whole_window_would(holes):
    """The means are computed over the cells they serve only: the band is
    the one computed with both over the whole window, bit for bit (the
    whole-window arithmetic: ``benchmarks/search_band.py``, which times
    the two)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from benchmarks.search_band import whole_window

    rng = np.random.default_rng(1)
    p = SearchParams()
    d = search_halo(p)
    coarse = 100 + np.cumsum(rng.normal(size=(70 + 2 * d, 64 + 2 * d)), axis=0)
    if holes == "scattered":
        coarse[rng.random(coarse.shape) < 0.3] = np.nan
        coarse[40:48, 20:29] = np.nan
    elif holes == "one big":
        coarse[d + 10 : d + 50, d + 5 : d + 45] = np.nan  # its middle lies beyond the fill support
    elif holes == "at the edges":
        coarse[:, : d + 3] = np.nan  # beyond the grid, into the core
        coarse[-d - 9 :, -d - 9 :] = np.nan
    elif holes == "halo only":
        coarse[: d - 4, :] = np.nan
    elif holes == "all":
        coarse[...] = np.nan
    got = search_from_coarse(coarse, d, 1.5, (60.0, 200.0), p)
    np.testing.assert_array_equal(got, whole_window(coarse, d, 1.5, (60.0, 200.0), p))
    if holes == "one big":
        assert np.isnan(got[0]).any() and np.isfinite(got[0]).mean() > 0.5
