"""Space intersection and tie points: synthetic round trips and the real
Pleiades pair of s2p (reference DSM heights 2270-2376 m)."""

import numpy as np
import pytest

from tiledsm.geometry import RPC
from tiledsm.match.tiepoints import height_range_from_tiepoints, match_tiepoints, relative_correction, supported
from tiledsm.match.triangulate import triangulate


def _s2p_rpcs(shared_data):
    import rasterio

    rpcs, imgs = [], []
    for name in ("img_01.tif", "img_02.tif"):
        with rasterio.open(shared_data("s2p_pair", "input_pair", name)) as ds:
            rpcs.append(RPC.from_gdal(ds.rpcs.to_dict(), source=name))
            imgs.append(ds.read(1).astype(np.float32))
    return rpcs, imgs


def test_triangulate_synthetic_round_trip(synthetic_scene):
    r1, r2 = synthetic_scene.rpcs
    rng = np.random.default_rng(0)
    rows, cols, h = rng.uniform(0, 200, 50), rng.uniform(30, 230, 50), rng.uniform(80, 130, 50)
    lon, lat = r1.localize(rows, cols, h)
    p1 = np.stack(r1.project(lon, lat, h), -1)
    p2 = np.stack(r2.project(lon, lat, h), -1)
    L, P, H, res = triangulate(r1, r2, p1, p2)
    assert np.abs(H - h).max() < 1e-6 and res.max() < 1e-6
    # a 0.8 px column error in image 2 is a 1 m height error at 0.8 px/m parallax (split: residual 0)
    L, P, H, res = triangulate(r1, r2, p1, p2 + [0.0, -0.8])
    assert np.allclose(H - h, 1.0, atol=1e-6)
    # a 1 px row error cannot be explained by a height (rows depend on latitude only): least
    # squares splits it, +-0.5 px in each image, RMS over the four coordinates sqrt(0.5 / 4)
    _, _, _, res = triangulate(r1, r2, p1, p2 + [1.0, 0.0])
    assert np.allclose(res, np.sqrt(0.125), atol=1e-4)


@pytest.mark.realdata
def test_triangulate_s2p_rpcs(shared_data):
    (r1, r2), _ = _s2p_rpcs(shared_data)
    rng = np.random.default_rng(1)
    row, col, h = rng.uniform(0, 1024, 500), rng.uniform(0, 1024, 500), rng.uniform(2250, 2400, 500)
    lon, lat = r1.localize(row, col, h)
    p1 = np.stack(r1.project(lon, lat, h), -1)
    p2 = np.stack(r2.project(lon, lat, h), -1)
    L, P, H, res = triangulate(r1, r2, p1, p2)
    assert np.abs(H - h).max() < 1e-6 and np.abs(L - lon).max() < 1e-10 and res.max() < 1e-6


@pytest.mark.realdata
def test_tiepoints_height_range_and_correction_s2p(shared_data):
    (r1, r2), (a, b) = _s2p_rpcs(shared_data)
    p1, p2 = match_tiepoints(a, b)
    assert len(p1) > 500
    lo, hi = height_range_from_tiepoints(r1, r2, p1, p2, margin=0.0)
    # s2p's DSM of this pair spans 2270-2376 m (supported tie-point extremes measured: 2268.6-2375.7)
    assert 2255 < lo < 2285 and 2360 < hi < 2390
    info = {}
    drow, dcol = relative_correction(r1, r2, p1, p2, details=info)
    # measured: (-0.15, -0.70) px; median epipolar residual 0.72 -> 0.17 px
    assert 0.3 < np.hypot(drow, dcol) < 1.5
    assert info["residual_after_px"] < 0.5 * info["residual_before_px"]
    r2c = r2.replace(line_off=r2.line_off + drow, samp_off=r2.samp_off + dcol)
    assert np.median(triangulate(r1, r2c, p1, p2)[3]) < np.median(triangulate(r1, r2, p1, p2)[3])


def test_supported_keeps_consistent_groups_and_drops_lone_heights():
    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(0, 400, (300, 2))])
    h_ground = 300.0 + 0.02 * ground[:, 0] + rng.normal(0, 0.5, 300)
    roof = np.array([[200.0, 200.0], [212.0, 200.0], [200.0, 212.0], [212.0, 212.0]])  # a 12 m roof, 4 corners
    lone = np.array([[50.0, 50.0], [350.0, 120.0]])  # mismatches: heights nobody near confirms
    xy = np.vstack([ground, roof, lone])
    h = np.concatenate([h_ground, [365.0, 365.1, 364.9, 365.0], [600.0, 100.0]])
    keep = supported(xy, h, radius=50.0, tol=5.0, min_support=2)
    assert keep[300:304].all()  # the roof survives: 3 consistent neighbours each
    assert not keep[304:].any()  # the lone heights do not
    assert keep[:300].mean() > 0.98
    # one corner alone is not a roof
    assert not supported(xy[[*range(300), 300, 304]], h[[*range(300), 300, 304]], 50.0, 5.0, 2)[300]


def test_height_range_reaches_a_roof_that_percentiles_would_drop(synthetic_scene):
    """400 ground tie points at 80..130 m, 3 on a roof at 160 m (0.7 % of
    them, above the 99th percentile): the range reaches the roof; a lone
    mismatch at 250 m does not stretch it."""
    r1, r2 = synthetic_scene.rpcs
    rng = np.random.default_rng(3)
    rows, cols = rng.uniform(20, 200, 400), rng.uniform(40, 220, 400)
    h = rng.uniform(80, 130, 400)
    rows = np.concatenate([rows, [100, 104, 100], [60]])
    cols = np.concatenate([cols, [100, 100, 104], [60]])
    h = np.concatenate([h, [160.0] * 3, [250.0]])
    assert np.percentile(h, 99) < 131
    lon, lat = r1.localize(rows, cols, h)
    p1 = np.stack(r1.project(lon, lat, h), -1)
    p2 = np.stack(r2.project(lon, lat, h), -1)
    lo, hi = height_range_from_tiepoints(r1, r2, p1, p2, margin=0.0)
    assert hi == pytest.approx(160.0, abs=1e-3)
    assert lo == pytest.approx(h[:400].min(), abs=1e-3)
