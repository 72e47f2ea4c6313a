"""Sub-pixel correlation of windows against known Fourier shifts (an exact
sub-pixel translation of a band-limited texture)."""

import numpy as np
import pytest
from shift_cases import fourier_shift, texture

from tiledsm.displace.correlate import CorrelationParams, correlate_windows, shifted_windows
from tiledsm.errors import InvalidOptionError

N = 384


def centres(step=8, margin=64, n=N):
    r, c = np.meshgrid(np.arange(margin, n - margin, step), np.arange(margin, n - margin, step), indexing="ij")
    return r.ravel(), c.ravel()


@pytest.mark.parametrize("dy, dx", [(0.0, 0.0), (0.3, -0.7), (2.45, -3.1), (-5.2, 6.8)])
def test_known_sub_pixel_shifts_are_recovered(dy, dx):
    rng = np.random.default_rng(5)
    base = texture()
    pre = base + rng.normal(size=base.shape) * 2
    post = fourier_shift(base, dy, dx) + rng.normal(size=base.shape) * 2
    r, c = centres()
    out = correlate_windows(pre, post, r, c)
    ey, ex = out[0] - dy, out[1] - dx
    assert np.isfinite(ey).mean() > 0.99
    # measured: |bias| <= 0.0023 px, NMAD 0.009-0.011 px (2 DN noise on a 200 DN texture)
    assert abs(np.nanmean(ey)) < 0.004 and abs(np.nanmean(ex)) < 0.004
    for e in (ey, ex):
        assert 1.4826 * np.nanmedian(np.abs(e - np.nanmedian(e))) < 0.014
    assert np.nanmedian(out[2]) > 0.95  # phase coherence of a pure shift


def test_flat_windows_are_nan_not_noise():
    rng = np.random.default_rng(0)
    pre = 100 + rng.normal(size=(N, N)) * 0.2  # sensor noise only: std 0.2 DN < min_texture
    post = 100 + rng.normal(size=(N, N)) * 0.2
    r, c = centres()
    out = correlate_windows(pre, post, r, c, CorrelationParams(min_texture=1.0))
    assert np.isnan(out[0]).all() and np.isnan(out[1]).all()
    assert (out[3] < 1.0).all()


def test_windows_with_too_much_nodata_are_nan():
    base = texture()
    post = fourier_shift(base, 0.4, 0.2)
    pre = base.copy()
    pre[:, : N // 2] = np.nan
    r, c = centres()
    out = correlate_windows(pre, post, r, c)
    left = c < N // 2 - 16  # windows wholly in the NaN half
    right = c > N // 2 + 40
    assert np.isnan(out[0][left]).all()
    assert np.isfinite(out[0][right]).mean() > 0.99


def test_lanczos_windows_at_an_integer_shift_are_the_pixels():
    img = texture()
    r, c = np.array([100, 150]), np.array([120, 60])
    w = shifted_windows(img, r, c, np.array([2.0, -1.0]), np.array([0.0, 3.0]), 16)
    np.testing.assert_allclose(w[0], img[102 - 8:102 + 8, 120 - 8:120 + 8], atol=1e-9)
    np.testing.assert_allclose(w[1], img[149 - 8:149 + 8, 63 - 8:63 + 8], atol=1e-9)


def test_bad_parameters_are_named():
    for kw, needle in (({"window": 31}, "window"), ({"step": 3}, "step"), ({"frequency_cut": 0}, "frequency_cut")):
        with pytest.raises(InvalidOptionError, match=needle):
            CorrelationParams(**kw)


def test_offsets_up_to_search_are_found_by_the_widened_coarse_window():
    base = texture(seed=4)
    post = fourier_shift(base, -11.6, 13.3)  # beyond a third of the 32 px window
    r, c = centres(margin=80)
    out = correlate_windows(base, post, r, c, CorrelationParams(search=16))
    assert np.isfinite(out[0]).mean() > 0.99
    assert np.nanmedian(out[0]) == pytest.approx(-11.6, abs=0.01)
    assert np.nanmedian(out[1]) == pytest.approx(13.3, abs=0.01)
    # the same offsets with the default search (8 px) are refused, not wrong
    small = correlate_windows(base, post, r, c, CorrelationParams(search=8))
    assert np.isnan(small[0]).mean() > 0.95


def test_formal_errors_follow_the_true_errors():
    """Rows 4-5 (the phase-plane fit's formal standard errors) grow with the
    noise as the true errors do (their ratio stays put, which is what the
    stable-terrain calibration of sigma needs), and per axis: a texture
    blurred along x gives x the larger formal error, as it does the larger
    true error."""
    from scipy import ndimage

    r, c = centres()
    ratios, formal = [], []
    for noise in (1.0, 4.0, 8.0):
        rng = np.random.default_rng(5)
        pre = texture() + rng.normal(size=(N, N)) * noise
        post = fourier_shift(texture(), 0.3, -0.7) + rng.normal(size=(N, N)) * noise
        out = correlate_windows(pre, post, r, c)
        formal.append(np.nanmedian(out[5]))
        ratios.append(np.nanstd(out[1] + 0.7) / formal[-1])
    # measured: true / formal 0.141, 0.127, 0.130; formal 0.036, 0.154, 0.322 px
    assert max(ratios) / min(ratios) < 1.2
    assert formal[1] / formal[0] == pytest.approx(4.0, rel=0.15) and formal[2] / formal[1] == pytest.approx(2.0, rel=0.15)
    base = ndimage.gaussian_filter(texture(), (0, 2.5), mode="wrap")
    base = 100 + (base - base.mean()) / base.std() * 30
    rng = np.random.default_rng(5)
    out = correlate_windows(base + rng.normal(size=(N, N)) * 2,
                            fourier_shift(base, 0.3, -0.7) + rng.normal(size=(N, N)) * 2, r, c)
    # measured: true errors y / x 0.013 / 0.036 px, formal 0.112 / 0.202 px
    assert np.nanstd(out[1] + 0.7) > 2 * np.nanstd(out[0] - 0.3)
    assert np.nanmedian(out[5]) > 1.5 * np.nanmedian(out[4])
