"""Structural tie-point matching (tiledsm.orient.structural): Wallis and
Förstner against analytic images, candidates and relaxation on hand-made
cases, and the extractor on a rendered scene against the truth."""

from __future__ import annotations

import sys
import typing
from pathlib import Path

import numpy as np
import pytest

from pydantic import ValidationError

from tiledsm.io.cameras import find_camera
from tiledsm.orient.spec import OrientSpec, StructuralParams
from tiledsm.orient.structural import curve_candidates, forstner, match_tile_structural, relax, wallis
from tiledsm.orient.tracks import EXTRACTORS, tie_point_tracks

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.tiepoints import score, true_positions  # noqa: E402


# ------------------------------------------------------------------ Wallis
def _sines(shape=(120, 130), a=200.0, b=100.0, period=11):
    """1000 + a sin(col) + b sin(row), ``period`` px: over any window of a
    whole number of periods the mean is 1000 and the variance (a^2 + b^2) / 2."""
    r, c = np.indices(shape)
    return 1000.0 + a * np.sin(2 * np.pi * c / period) + b * np.sin(2 * np.pi * r / period + 0.3)


@pytest.mark.parametrize("c, b", [(1.0, 1.0), (0.6, 0.5)])
def test_wallis_reaches_the_target_statistics(c, b):
    g = _sines()
    p = StructuralParams(wallis_window=33, target_mean=127.0, target_std=50.0, contrast=c, brightness=b)
    out = wallis(g, p)
    sg = np.sqrt((200.0**2 + 100.0**2) / 2)
    r1 = c * 50.0 / (c * sg + (1 - c) * 50.0)
    # an interior block of 3 x 3 periods: every pixel's window is whole periods
    blk = out[40:73, 40:73].astype(np.float64)
    assert blk.mean() == pytest.approx(b * 127.0 + (1 - b) * 1000.0, abs=1e-3)
    assert blk.std() == pytest.approx(r1 * sg, rel=1e-4)
    if c == 1.0 and b == 1.0:
        assert blk.std() == pytest.approx(50.0, rel=1e-4)


def test_wallis_keeps_nodata_local():
    g = _sines()
    g[60, 60] = np.nan
    p = StructuralParams(wallis_window=33)
    out = wallis(g, p)
    assert np.isnan(out[60, 60]) and np.isfinite(np.delete(out.ravel(), 60 * g.shape[1] + 60)).all()
    ref = wallis(_sines(), p)
    np.testing.assert_allclose(out[:, 100:], ref[:, 100:], atol=1e-3)  # windows clear of the hole


# ------------------------------------------------------------------ Förstner
def test_forstner_finds_checkerboard_corners_only():
    i, j = np.indices((64, 64))
    board = ((i // 8 + j // 8) % 2) * 100.0
    pos, w = forstner(board)
    corners = np.array([(8.0 * a, 8.0 * b) for a in range(1, 8) for b in range(1, 8)])  # GDAL
    d = np.hypot(*(pos[:, None] - corners[None]).transpose(2, 0, 1))
    assert (d.min(axis=0) < 0.5).all(), "a corner was missed"
    assert (d.min(axis=1) < 0.5).all(), "a point off the corners (an edge?)"
    assert len(pos) == len(corners) and np.all(np.diff(w) <= 0)


def test_forstner_finds_rectangle_corners_not_edges():
    img = np.zeros((80, 100))
    rects = [(10, 30, 15, 60, 100.0), (45, 70, 30, 50, 60.0), (40, 75, 70, 90, 140.0)]
    for r0, r1, c0, c1, v in rects:
        img[r0:r1, c0:c1] = v
    corners = np.array([(r, c) for r0, r1, c0, c1, _ in rects for r in (r0, r1) for c in (c0, c1)], float)
    pos, _ = forstner(img, StructuralParams(max_offset_px=2.5))
    d = np.hypot(*(pos[:, None] - corners[None]).transpose(2, 0, 1))
    assert (d.min(axis=0) < 0.5).all() and (d.min(axis=1) < 0.5).all()
    assert len(pos) == len(corners)
    # by default, L-shaped corners (w maximum 1.5 px inside) are dropped
    assert len(forstner(img)[0]) == 0


# ------------------------------------------------------------------ candidates
def test_curve_candidates_find_both_peaks_of_a_repeated_pattern():
    u, v = np.indices((60, 30), dtype=float)
    peaks = [(15.3, 12.6), (40.3, 12.6)]  # equal, 1.6 px across the curve (the guide's leftover)
    res = sum(0.9 * np.exp(-((u - a) ** 2 + (v - b) ** 2) / 4.0) for a, b in peaks)
    curve = np.column_stack([np.linspace(2, 57, 56), np.full(56, 11.0)])
    c = curve_candidates(res, curve, StructuralParams(min_ncc=0.5))
    assert len(c["ncc"]) == 2 and np.all(c["ncc"] > 0.84)
    got = c["pos"][np.argsort(c["pos"][:, 0])]
    np.testing.assert_allclose(got, peaks, atol=0.15)
    np.testing.assert_allclose(np.sort(c["s"]), [13.3, 38.3], atol=0.6)
    # none above the threshold: no candidate
    assert len(curve_candidates(0.3 * res, curve, StructuralParams(min_ncc=0.5))["ncc"]) == 0


# ------------------------------------------------------------------ relaxation
def _grid():
    """3 x 3 points 10 px apart; the centre is point 4."""
    return np.array([(r, c) for r in (0, 10, 20) for c in (0, 10, 20)], float)


def test_relaxation_lets_the_neighbours_choose():
    xy = _grid()
    ncc = np.full((9, 2), np.nan)
    s = np.full((9, 2), np.nan)
    ncc[:, 0], s[:, 0] = 0.9, 20.0  # every neighbour: one candidate at parallax 20
    ncc[4], s[4] = (0.9, 0.9), (8.0, 20.0)  # the centre: two equal peaks, the wrong one first
    choice, prob = relax(ncc, s, xy)
    assert choice[4] == 1 and prob[4] > 0.9
    assert np.all(choice[np.arange(9) != 4] == 0)
    # the same centre among neighbours at parallax 8 takes the other one
    s2 = s.copy()
    s2[np.arange(9) != 4, 0] = 8.0
    assert relax(ncc, s2, xy)[0][4] == 0


def test_relaxation_drops_a_point_its_neighbours_contradict():
    xy = _grid()
    ncc = np.full((9, 1), 0.9)
    s = np.full((9, 1), 20.0)
    s[4] = 45.0  # as good an NCC as theirs, an incompatible parallax
    choice, _ = relax(ncc, s, xy)
    assert choice[4] == -1 and np.all(choice[np.arange(9) != 4] == 0)
    # alone (no neighbour within the radius) it keeps its initial odds: taken at 0.9, not at 0.65
    far = xy.copy()
    far[4] = (500.0, 500.0)
    assert relax(ncc, s, far)[0][4] == 0
    ncc[4] = 0.65
    assert relax(ncc, s, far)[0][4] == -1


# ------------------------------------------------------------------ registry
def test_extractor_is_chosen_by_name():
    # the spec names the registry's keys, and nothing else
    assert set(EXTRACTORS) == {"features", "structural"}
    assert set(typing.get_args(OrientSpec.model_fields["extractor"].annotation)) == set(EXTRACTORS)
    with pytest.raises(ValidationError, match="extractor"):
        OrientSpec(extractor="sift")
    with pytest.raises(ValidationError, match="template"):
        StructuralParams(template=14)


# ------------------------------------------------------------------ a rendered scene
def test_truth_oracle_is_consistent(scene2):
    """The benchmark's truth: true positions intersect with the true cameras
    without residual, on the truth DSM."""
    import rasterio
    from pyproj import Transformer
    from scipy.ndimage import map_coordinates

    from tiledsm.orient.adjust import intersect

    info, true, *_ = scene2
    ref = np.random.default_rng(0).uniform(100, 400, (40, 2))
    pos, _ = true_positions(ref, true, info.out_dir)
    ok = np.isfinite(pos[1, :, 0])
    assert ok.mean() > 0.9
    n = int(ok.sum())
    img, pt = np.repeat([0, 1], n), np.tile(np.arange(n), 2)
    g, res = intersect(true, img, pt, pos[:, ok, 0].ravel(), pos[:, ok, 1].ravel(), n)
    assert np.abs(res).max() < 0.01
    with rasterio.open(info.truth_dsm) as ds:
        x, y = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True).transform(g[:, 0], g[:, 1])
        t = ~ds.transform
        col, row = t.a * x + t.b * y + t.c, t.d * x + t.e * y + t.f
        z = map_coordinates(ds.read(1).astype(float), [row - 0.5, col - 0.5], order=1)
    assert np.abs(g[:, 2] - z).max() < 0.1


#: measured on scene2 (tiles of 256): tracks, scored matches, share within 1 px of the truth,
#: clear matches (one smooth visible surface under the template), median error px
MEASURED = {"features": (478, 454, 0.751, 258, 0.30), "structural": (482, 459, 0.758, 289, 0.33)}


@pytest.mark.parametrize("extractor", ["structural", "features"])
def test_extractors_against_truth(scene2, extractor):
    """The misses (about a quarter) sit at walls and roof borders, where the
    template follows the strongest edge; every clear match is within 1 px."""
    info, true, biased, h, root = scene2
    rpcs = [find_camera(p)[0] for p in biased]
    spec = OrientSpec(tile=256, extractor=extractor)
    tracks, guide = tie_point_tracks(biased, rpcs, spec, scheduler="synchronous")
    truth, clear = true_positions(tracks.pos[0], true, info.out_dir)
    s = score(tracks.pos, truth, clear)
    print(extractor, tracks.n, s)
    n, m, c1, nc, med = MEASURED[extractor]
    assert tracks.n > 0.94 * n and s["matches"] > 0.94 * m
    assert s["correct_1px"] > c1 - 0.03 and s["median_error_px"] < med + 0.07
    assert s["correct_clear_1px"] > 0.98 and s["clear_matches"] > 0.9 * nc
    if extractor == "structural":
        # one tile by hand, with the StructuralParams themselves: the contract of match_tile
        out = match_tile_structural(biased, rpcs, guide, (0, 256, 0, 256), spec.tracks.structural)
        assert out["pos"].shape[0] == 2 and np.all(out["ncc"][0] == 1.0)
        assert np.all((out["pos"][0] >= 0) & (out["pos"][0] < 256))
