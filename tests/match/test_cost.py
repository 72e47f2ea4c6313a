"""ZNCC cost against a brute-force numpy oracle."""

import numpy as np
import pytest

from tiledsm.match.cost import mean_zncc_cost, zncc_cost


def _oracle(a, b, half):
    ny, nx = a.shape
    out = np.full((ny, nx), np.nan)
    for i in range(half, ny - half):
        for j in range(half, nx - half):
            wa = a[i - half : i + half + 1, j - half : j + half + 1].astype(float).ravel()
            wb = b[i - half : i + half + 1, j - half : j + half + 1].astype(float).ravel()
            if not (np.isfinite(wa).all() and np.isfinite(wb).all()):
                continue
            out[i, j] = 1 - np.corrcoef(wa, wb)[0, 1]
    return out


@pytest.mark.parametrize("half", [0 + 1, 2, 3])
def test_zncc_matches_bruteforce_with_nodata(half):
    rng = np.random.default_rng(half)
    a = rng.normal(100, 20, (23, 31)).astype(np.float32)
    b = (0.5 * a + rng.normal(0, 10, a.shape)).astype(np.float32)
    a[5, 7] = np.nan
    b[15, 20] = np.nan
    got = zncc_cost(a, b, half)
    ref = _oracle(a, b, half)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) < 1e-5
    assert np.nanmin(got) >= 0 and np.nanmax(got) <= 2


def test_zncc_affine_invariance_and_flat_windows():
    rng = np.random.default_rng(0)
    a = rng.random((20, 20)).astype(np.float32)
    c = zncc_cost(a, 3 * a + 7, 2)
    assert np.nanmax(c) < 1e-5
    assert np.nanmin(zncc_cost(a, -a, 2)) > 2 - 1e-5
    flat = np.full_like(a, 5.0)
    assert np.isnan(zncc_cost(a, flat, 2)).all()
    # writes into a strided view of a cost volume
    vol = np.zeros((20, 20, 3), np.float32)
    zncc_cost(a, 3 * a + 7, 2, out=vol[:, :, 1])
    assert np.nanmax(vol[2:-2, 2:-2, 1]) < 1e-5 and np.all(vol[:, :, 0] == 0)


def test_mean_zncc_three_views_ignores_invalid_pairs():
    rng = np.random.default_rng(1)
    v = [rng.random((15, 15)).astype(np.float32) for _ in range(3)]
    v[2][7, 7] = np.nan
    got = mean_zncc_cost(v, 1)
    c01, c02, c12 = zncc_cost(v[0], v[1], 1), zncc_cost(v[0], v[2], 1), zncc_cost(v[1], v[2], 1)
    stack = np.stack([c01, c02, c12])
    n = np.isfinite(stack).sum(axis=0)
    ref = np.where(n > 0, np.nansum(stack, axis=0) / np.maximum(n, 1), np.nan)
    assert np.allclose(got, ref, equal_nan=True, atol=1e-6)
    # around the nodata pixel only the (0, 1) pair is valid
    assert got[7, 7] == pytest.approx(c01[7, 7], abs=1e-6)


def test_mean_zncc_pair_weights():
    rng = np.random.default_rng(2)
    v = [rng.random((15, 15)).astype(np.float32) for _ in range(3)]
    v[2][7, 7] = np.nan
    w = np.array([[0, 4.0, 1.0], [0, 0, 0.25], [0, 0, 0]])
    got = mean_zncc_cost(v, 1, weights=w)
    c = np.stack([zncc_cost(v[0], v[1], 1), zncc_cost(v[0], v[2], 1), zncc_cost(v[1], v[2], 1)])
    wk = np.array([4.0, 1.0, 0.25])[:, None, None] * np.isfinite(c)
    ref = np.nansum(wk * np.nan_to_num(c), axis=0) / wk.sum(axis=0)
    assert np.allclose(got, ref, atol=1e-6, equal_nan=True)
    assert got[7, 7] == pytest.approx(c[0, 7, 7], abs=1e-6)  # only the (0, 1) pair is valid there
    with pytest.raises(ValueError, match="weights"):
        mean_zncc_cost(v, 1, weights=np.ones((2, 2)))
