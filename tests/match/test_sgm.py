"""Semi-global aggregation against a direct (slow) implementation of the
recursion in absolute labels, WTA and speckle filter against oracles."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy import ndimage

from tiledsm.match.sgm import aggregate, aggregate_best, remove_speckles, winner_take_all

DIRS = [(0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)]


def _reference(cost, base, P1, P2, guide=None, gamma=1.0, nvalid=None):
    ny, nx, nd = cost.shape
    nv = np.full((ny, nx), nd) if nvalid is None else nvalid
    S = np.zeros(cost.shape)
    for dy, dx in DIRS:
        L = np.full(cost.shape, np.inf)
        ys = range(ny) if dy >= 0 else range(ny - 1, -1, -1)
        xs = list(range(nx)) if dx >= 0 else list(range(nx - 1, -1, -1))
        for i in ys:
            for j in xs:
                n = nv[i, j]
                pi, pj = i - dy, j - dx
                # the volume's edge or a gap (a cell without candidates): the path starts here
                if not (0 <= pi < ny and 0 <= pj < nx) or nv[pi, pj] == 0:
                    L[i, j, :n] = cost[i, j, :n]
                    continue
                p2 = P2
                if guide is not None:
                    p2 = max(P1, P2 / (1 + abs(guide[i, j] - guide[pi, pj]) / gamma))
                prev = L[pi, pj, : nv[pi, pj]]
                m = prev.min()
                for k in range(n):
                    lab = base[i, j] + k
                    dl = np.abs(base[pi, pj] + np.arange(prev.size) - lab)
                    pen = np.where(dl == 0, 0.0, np.where(dl == 1, P1, p2))
                    L[i, j, k] = cost[i, j, k] + min((prev + pen).min(), m + p2) - m
        S += L
    return S


@pytest.mark.parametrize("with_base", [False, True])
def test_aggregate_matches_reference(with_base):
    rng = np.random.default_rng(3)
    cost = rng.random((6, 8, 5)).astype(np.float32)
    base = rng.integers(-2, 3, (6, 8)) if with_base else np.zeros((6, 8), int)
    S = aggregate(cost, 0.1, 0.7, base=base)
    assert np.abs(S - _reference(cost, base, 0.1, 0.7)).max() < 1e-5


@pytest.mark.parametrize("fast", [False, True], ids=["reference", "fast"])
def test_absent_candidates_never_enter_a_path(fast):
    """Cells with fewer candidates than the volume is deep, and gaps
    without any: the result is the recursion over the candidates that
    exist, whatever the padding holds and however deep it is (the
    padded cost 4.0 exceeds any real cost plus P2, so it would win path
    steps if it took part)."""
    rng = np.random.default_rng(5)
    ny, nx, nd = 9, 11, 6
    cost = rng.random((ny, nx, nd)).astype(np.float32) * 2
    base = rng.integers(-4, 5, (ny, nx))
    nvalid = rng.integers(1, nd + 1, (ny, nx))
    nvalid[4, 2:9] = 0  # a gap across the paths
    nvalid[1, 1] = 0
    present = np.arange(nd) < nvalid[..., None]
    ref = _reference(cost, base, 0.3, 2.0, nvalid=nvalid)
    for pad, depth in ((4.0, 0), (4.0, 5), (0.0, 3), (np.nan, 2)):
        padded = np.where(present, cost, np.float32(pad))
        padded = np.concatenate([padded, np.full((ny, nx, depth), pad, np.float32)], axis=2)
        S = aggregate(padded, 0.3, 2.0, base=base, nvalid=nvalid, fast=fast)
        assert np.abs(S[..., :nd][present] - ref[present]).max() < 1e-5
        assert np.isposinf(S[..., :nd][~present]).all() and np.isposinf(S[..., nd:]).all()


def _ragged_volume(seed: int, ny: int, nx: int, nd: int, shift: int):
    """Random costs (5 % NaN), bases in ``-shift..shift`` and ``0..nd``
    candidates per cell."""
    rng = np.random.default_rng(seed)
    cost = (rng.random((ny, nx, nd)) * 2).astype(np.float32)
    cost[rng.random(cost.shape) < 0.05] = np.nan
    return cost, rng.integers(-shift, shift + 1, (ny, nx)), rng.integers(0, nd + 1, (ny, nx))


# depth, base spread: fewer candidates than the fixed lanes (16), with jumps
# past the slots' guard (4) and past the depth; then cells on both sides of
# the lanes, sharing the path slots
DEPTHS = [(9, 5), (40, 12), (20, 15)]


@pytest.mark.parametrize("nd, shift", DEPTHS)
def test_fast_aggregation_equals_reference_bit_for_bit(nd, shift):
    cost, base, nvalid = _ragged_volume(6, 30, 37, nd, shift)
    for period in (0, 8):
        kw = dict(base=base, nvalid=nvalid, restart_period=period, origin=(3, 5))
        assert np.array_equal(aggregate(cost, 0.3, 2.0, **kw), aggregate(cost, 0.3, 2.0, fast=True, **kw))


@pytest.mark.parametrize("nd, shift", DEPTHS)
def test_winners_taken_in_the_last_pass_equal_aggregate_then_wta(nd, shift):
    """aggregate_best gives winner_take_all's four arrays bit for bit, with
    cells of 0..nd candidates, shifted bases, NaN costs and restarts."""
    cost, base, nvalid = _ragged_volume(7, 33, 29, nd, shift)
    for period in (0, 8):
        kw = dict(base=base, nvalid=nvalid, restart_period=period, origin=(2, 7))
        want = winner_take_all(aggregate(cost, 0.3, 2.0, fast=True, **kw), cost, nvalid)
        got = aggregate_best(cost, 0.3, 2.0, **kw)
        assert np.isnan(want[0]).any() and np.isfinite(want[0]).mean() > 0.8
        for a, b in zip(got, want):
            assert np.array_equal(a, b, equal_nan=True)


def test_aggregate_adaptive_p2_and_nan():
    rng = np.random.default_rng(4)
    cost = rng.random((5, 7, 4)).astype(np.float32)
    guide = rng.normal(0, 20, (5, 7)).astype(np.float32)
    S = aggregate(cost, 0.1, 0.9, guide=guide, p2_gamma=10.0)
    ref = _reference(cost, np.zeros((5, 7), int), 0.1, 0.9, guide, 10.0)
    assert np.abs(S - ref).max() < 1e-5
    cost[2, 3, :] = np.nan
    S = aggregate(cost, 0.1, 0.9, invalid_cost=1.0)
    filled = np.where(np.isnan(cost), 1.0, cost)
    assert np.abs(S - _reference(filled, np.zeros((5, 7), int), 0.1, 0.9)).max() < 1e-5


def test_sgm_regularises_noisy_plane():
    # a constant true label under strong noise: aggregation recovers it where raw WTA fails
    rng = np.random.default_rng(5)
    nd = 9
    cost = (np.abs(np.arange(nd) - 4)[None, None, :] * 0.15 + rng.random((40, 40, nd)) * 0.6).astype(np.float32)
    raw = np.argmin(cost, axis=2)[4:-4, 4:-4]
    idx, _, _, _ = winner_take_all(aggregate(cost, 0.5, 2.0), cost)
    assert np.mean(raw == 4) < 0.6
    assert np.mean(np.abs(idx[4:-4, 4:-4] - 4) < 0.5) > 0.97


def test_wta_parabola_exact_on_quadratic_and_nvalid():
    x0 = np.array([[2.3, 5.75], [1.5, 3.0]])
    k = np.arange(8)
    S = ((k[None, None, :] - x0[..., None]) ** 2).astype(np.float32)
    idx, smin, ratio, cbest = winner_take_all(S)
    assert np.allclose(idx, x0, atol=1e-4)
    assert np.all(ratio < 1)
    # candidates beyond nvalid are ignored
    idx2, *_ = winner_take_all(S, nvalid=np.array([[3, 8], [8, 8]]))
    assert idx2[0, 0] == pytest.approx(2.0)


def test_remove_speckles_matches_connected_components():
    rng = np.random.default_rng(6)
    labels = rng.integers(0, 4, (30, 30)).astype(np.float32)
    labels = ndimage.median_filter(labels, 3).astype(np.float32)
    labels[3, 3] = 50.0  # an isolated cell
    out = remove_speckles(labels, 0.0, 6)
    expected = labels.copy()
    for v in np.unique(labels):
        lab, n = ndimage.label(labels == v)  # 4-connectivity
        sizes = ndimage.sum(np.ones_like(labels), lab, index=np.arange(1, n + 1))
        for c, sz in enumerate(sizes, start=1):
            if sz < 6:
                expected[lab == c] = np.nan
    assert np.isnan(out[3, 3])
    assert np.array_equal(np.isnan(out), np.isnan(expected))


# the volumes of the bit-for-bit tests above, this module imported by path
_IN_BOUNDS = """
import sys
sys.path.insert(0, {here!r})
from test_sgm import DEPTHS, _ragged_volume
from tiledsm.match.sgm import aggregate, aggregate_best
for nd, shift in DEPTHS:
    cost, base, nvalid = _ragged_volume(1, 17, 23, nd, shift)
    for period in (0, 8):
        kw = dict(base=base, nvalid=nvalid, restart_period=period, origin=(3, 5))
        aggregate(cost, 0.3, 2.0, fast=True, **kw)
        aggregate_best(cost, 0.3, 2.0, **kw)
"""


def test_fast_passes_index_only_inside_their_arrays(tmp_path):
    """The compiled passes recompiled with numba's bounds checks: any index
    outside an array raises (unchecked, such a read returns whatever lies
    beyond, or faults when that is unmapped: a neighbour row read before
    the volume's first row did on a 576² volume)."""
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = subprocess.run([sys.executable, "-c", _IN_BOUNDS.format(here=os.path.dirname(__file__))], env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
