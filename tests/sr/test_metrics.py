"""PSNR / SSIM against analytic values and scikit-image."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from tiledsm.sr import psnr, ssim


def test_psnr_analytic_bit_depth():
    ref = np.zeros((10, 10))
    test = np.full((10, 10), 5.0)
    # MSE = 25 -> PSNR = 10 log10(peak^2 / 25)
    assert psnr(ref, test, bit_depth=8) == pytest.approx(10 * np.log10(255**2 / 25))
    assert psnr(ref, test, bit_depth=12) == pytest.approx(10 * np.log10(4095**2 / 25))
    assert psnr(ref, ref, bit_depth=8) == np.inf
    with pytest.raises(ValueError, match="bit_depth"):
        psnr(ref, test)


def test_psnr_matches_skimage_and_ignores_nan():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 4095, (40, 50))
    test = ref + rng.normal(0, 30, ref.shape)
    expected = peak_signal_noise_ratio(ref[3:-3, 3:-3], test[3:-3, 3:-3], data_range=4095)
    assert psnr(ref, test, bit_depth=12, border=3) == pytest.approx(expected, rel=1e-12)
    holed = test.copy()
    holed[:, :10] = np.nan
    assert psnr(ref, holed, data_range=4095) == pytest.approx(peak_signal_noise_ratio(ref[:, 10:], test[:, 10:], data_range=4095))


def test_ssim_matches_skimage_and_handles_nan():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0, 255, (60, 60))
    test = ref + rng.normal(0, 20, ref.shape)
    assert ssim(ref, ref, bit_depth=8) == pytest.approx(1.0)
    expected = structural_similarity(ref[2:-2, 2:-2], test[2:-2, 2:-2], data_range=255)
    assert ssim(ref, test, bit_depth=8, border=2) == pytest.approx(expected, rel=1e-12)
    # NaN in the left 20 columns: equals skimage's mean over windows of the right part
    holed = test.copy()
    holed[:, :20] = np.nan
    _, smap = structural_similarity(ref[:, 20:], test[:, 20:], data_range=255, full=True)
    assert ssim(ref, holed, bit_depth=8) == pytest.approx(smap[3:-3, 3:-3].mean(), rel=1e-9)
