"""Per-cell sigma from stable terrain: heteroscedastic bins, the variogram
and the error of a mean, against synthetic errors of known spread."""

import numpy as np
import pytest
from scipy import ndimage

from tiledsm.displace.uncertainty import binned_sigma, coverage, fit_variogram, mean_error


def test_binned_sigma_follows_a_predictor_and_covers_95_percent():
    rng = np.random.default_rng(0)
    n = 200
    q = rng.uniform(0, 1, (n, n))
    true_sigma = 0.01 + 0.05 * (1 - q)  # worse matches, larger errors
    err = rng.normal(size=(n, n)) * true_sigma
    stable = np.zeros((n, n), bool)
    stable[:, : n // 2] = True
    sigma, table = binned_sigma(err, stable, {"quality": q}, bins=8)
    # on the other half (not used to estimate): the sigma of each bin is the true one within 10 %
    ratio = sigma[:, n // 2:] / true_sigma[:, n // 2:]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert coverage(err[:, n // 2:], sigma[:, n // 2:]) == pytest.approx(0.954, abs=0.02)
    assert len(table["sigma"]) == 8


def test_variogram_of_white_noise_has_no_correlated_part():
    rng = np.random.default_rng(1)
    z = rng.normal(size=(120, 120))
    x = np.arange(120) * 4.0
    y = -np.arange(120) * 4.0
    v, emp = fit_variogram(z, x, y, np.ones(z.shape, bool))
    assert v.nugget + v.sill == pytest.approx(1.0, abs=0.1)
    assert v.sill < 0.1


def test_correlated_errors_make_the_mean_less_certain_than_sqrt_n():
    rng = np.random.default_rng(2)
    z = ndimage.gaussian_filter(rng.normal(size=(150, 150)), 6)
    z /= z.std()
    x = np.arange(150) * 4.0
    y = -np.arange(150) * 4.0
    v, _ = fit_variogram(z, x, y, np.ones(z.shape, bool))
    assert v.sill > 0.7 and 20 < v.range_m < 150  # smoothing of 6 cells (24 m) -> correlated over ~2-4 sigma
    cells = np.zeros(z.shape, bool)
    cells[:40, :40] = True
    sigma = np.ones(z.shape)
    e = mean_error(sigma, x, y, cells, v)
    assert e > 5 / np.sqrt(cells.sum())
    # against the spread of the means of many independent 40 x 40 blocks of such fields
    means = []
    for s in range(40):
        f = ndimage.gaussian_filter(np.random.default_rng(100 + s).normal(size=(150, 150)), 6)
        means.append((f / f.std())[:40, :40].mean())
    assert e == pytest.approx(np.std(means), rel=0.5)
