"""World determinism, texture spectrum, object placement."""

from __future__ import annotations

import numpy as np

from tiledsm.synth import make_world
from tiledsm.synth.noise import power_law_field


def test_world_is_deterministic_by_seed():
    x = np.arange(-40.0, 40.0, 0.5)
    y = np.arange(10.0, 70.0, 0.5)
    h1, a1, l1 = make_world(5, 0.5).evaluate(x, y)
    h2, a2, l2 = make_world(5, 0.5).evaluate(x, y)
    h3, _, _ = make_world(6, 0.5).evaluate(x, y)
    assert np.array_equal(h1, h2) and np.array_equal(a1, a2) and np.array_equal(l1, l2)
    assert np.abs(h1 - h3).max() > 1.0


def test_world_windows_are_seamless():
    """A window evaluated alone equals the same cells of a larger window."""
    w = make_world(1, 0.5)
    x = np.arange(-200.0, 200.0, 0.5)
    y = np.arange(-150.0, 150.0, 0.5)
    h, a, lab = w.evaluate(x, y)
    hs, as_, ls = w.evaluate(x[300:500], y[100:260])
    np.testing.assert_allclose(hs, h[100:260, 300:500], atol=2e-3)
    np.testing.assert_allclose(as_, a[100:260, 300:500], atol=2e-5)
    assert (ls != lab[100:260, 300:500]).mean() < 1e-3
    # all three classes are present and buildings have vertical walls
    assert set(np.unique(lab)) == {0, 1, 2}
    dh = np.abs(np.diff(h, axis=1))[(lab[:, 1:] == 1) != (lab[:, :-1] == 1)]
    assert np.median(dh) > 3.0


def test_height_bounds_hold():
    w = make_world(2, 0.5)
    lo, hi = w.height_bounds(-300, 300, -300, 300)
    h, _, _ = w.evaluate(np.arange(-300, 300, 1.0), np.arange(-300, 300, 1.0))
    assert lo <= h.min() and h.max() <= hi
    assert hi - lo < 4 * (h.max() - h.min()) + 50  # not absurdly loose


def _psd_slope(field, n=512, step=1.0):
    x = np.arange(n) * step
    img = field.grid(x, x, dtype=np.float64)
    win = np.hanning(n)[:, None] * np.hanning(n)[None, :]
    p = np.abs(np.fft.fftshift(np.fft.fft2((img - img.mean()) * win))) ** 2
    f = np.fft.fftshift(np.fft.fftfreq(n, step))
    fr = np.hypot(*np.meshgrid(f, f))
    edges = np.geomspace(8.0 / (n * step), 0.3 / step, 12)
    centres, power = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (fr >= lo) & (fr < hi)
        centres.append(np.sqrt(lo * hi))
        power.append(p[m].mean())
    return np.polyfit(np.log(centres), np.log(power), 1)[0]


def test_texture_spectrum_slope_is_the_designed_one():
    w = make_world(0, 0.5)
    slope = _psd_slope(w.albedo_field, step=0.5)
    assert abs(slope - (-w.texture.beta)) < 0.3, slope
    rng = np.random.default_rng(4)
    steep = power_law_field(rng, (1.0, 2000.0), 3.0, 1.0, 40)
    assert abs(_psd_slope(steep) + 3.0) < 0.3


def test_texture_is_band_limited_and_unit_variance():
    w = make_world(0, 0.5)
    k = np.hypot(w.albedo_field.kx, w.albedo_field.ky)
    assert k.max() <= 2 * np.pi / (2 * 0.5)  # below the image Nyquist
    assert abs(w.albedo_field.rms - 1.0) < 1e-12
    x = np.arange(0, 2000.0, 0.5)
    v = w.albedo_field.grid(x, x[:400], dtype=np.float64)
    assert 0.5 < v.std() < 1.5
