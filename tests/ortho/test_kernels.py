"""Interpolation kernels against the cubic-convolution formula and OpenCV."""

import cv2
import numpy as np
import pytest

from tiledsm.errors import InvalidOptionError
from tiledsm.ortho.kernels import KERNELS, Kernel, cubic_weight, get_kernel, sample


def _keys(t, a):
    """The published weight function, written independently (numpy)."""
    t = np.abs(t)
    return np.where(t <= 1, (a + 2) * t**3 - (a + 3) * t**2 + 1,
                    np.where(t <= 2, a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a, 0.0))


@pytest.mark.parametrize("name,a", [("cr", -1.0), ("cs", -0.5)])
def test_cubic_weight_is_the_formula(name, a):
    assert KERNELS[name].a == a
    t = np.linspace(-2.5, 2.5, 1001)
    got = np.array([cubic_weight(v, a) for v in t])
    np.testing.assert_allclose(got, _keys(t, a), atol=1e-12)
    # interpolating kernel: w(0) = 1, w(+-1) = w(+-2) = 0, partition of unity
    assert cubic_weight(0.0, a) == 1.0 and cubic_weight(1.0, a) == 0.0 and cubic_weight(2.0, a) == 0.0
    f = 0.37
    assert sum(cubic_weight(f - m, a) for m in range(-1, 3)) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", ["cr", "cs"])
def test_cubic_sample_equals_separable_formula(name):
    rng = np.random.default_rng(1)
    img = rng.normal(size=(12, 14))
    k = KERNELS[name]
    r, c = 5.5 + rng.uniform(0, 1, 50), 6.5 + rng.uniform(0, 1, 50)  # GDAL coords, away from borders
    got = sample(img, r, c, name)
    y, x = r - 0.5, c - 0.5
    iy, ix = np.floor(y).astype(int), np.floor(x).astype(int)
    want = np.zeros(r.size)
    for m in range(-1, 3):
        for q in range(-1, 3):
            want += _keys(y - (iy + m), k.a) * _keys(x - (ix + q), k.a) * img[iy + m, ix + q]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_simon_reproduces_quadratics_rifman_does_not():
    # Keys: a = -0.5 is third-order accurate (exact on quadratics); a = -1 is not
    yy, xx = np.mgrid[0:20, 0:20].astype(float)
    img = 0.3 * xx**2 - 0.2 * xx * yy + yy
    r, c = np.array([9.83, 10.21]), np.array([8.64, 11.07])
    truth = 0.3 * (c - 0.5) ** 2 - 0.2 * (c - 0.5) * (r - 0.5) + (r - 0.5)
    np.testing.assert_allclose(sample(img, r, c, "cs"), truth, atol=1e-4)
    assert np.abs(sample(img, r, c, "cr") - truth).max() > 0.01


def _cv_remap(img, r, c, flag):
    # cv2 centres pixel [i, j] at (i, j): GDAL - 0.5
    return cv2.remap(img.astype(np.float32), (c - 0.5).astype(np.float32), (r - 0.5).astype(np.float32),
                     flag, borderMode=cv2.BORDER_REPLICATE)


@pytest.mark.parametrize("name,flag,kernel", [
    ("nn", cv2.INTER_NEAREST, "nn"),
    ("bl", cv2.INTER_LINEAR, "bl"),
    # a = -0.75 is OpenCV's cubic: checks the cubic path against an independent implementation
    ("cubic-0.75", cv2.INTER_CUBIC, Kernel("cv-cubic", 2, a=-0.75)),
])
def test_against_opencv_remap(name, flag, kernel):
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1000, size=(40, 50)).astype(np.float32)
    # OpenCV's remap quantises positions to 1/32 pixel: sample on that lattice
    # (shifted off the NN tie points), including the replicated borders
    r = (rng.integers(0, 40 * 32, size=(30, 30)) + 0.5) / 32 + 0.0
    c = (rng.integers(0, 50 * 32, size=(30, 30)) + 0.5) / 32
    if name != "nn":
        r, c = np.round(r * 32) / 32, np.round(c * 32) / 32
        r, c = np.clip(r, 0, 40), np.clip(c, 0, 50)
    got = sample(img, r, c, kernel)
    want = _cv_remap(img, r, c, flag)
    np.testing.assert_allclose(got, want, rtol=0, atol=0.05 if name != "nn" else 0)


def test_window_equals_whole_image_and_outside_is_nan():
    rng = np.random.default_rng(3)
    img = rng.normal(size=(30, 30))
    r, c = rng.uniform(10, 20, 100), rng.uniform(10, 20, 100)
    for k in KERNELS:
        whole = sample(img, r, c, k)
        win = sample(img[7:23, 8:24], r, c, k, origin=(7, 8), shape=img.shape)
        np.testing.assert_array_equal(whole, win)
    out = sample(img, np.array([-0.01, 15.0, 30.01]), np.array([5.0, 31.0, 5.0]), "bl")
    assert np.isnan(out).all()
    edge = sample(img, np.array([0.0, 30.0]), np.array([0.0, 30.0]), "bl")  # corners: replicated border
    np.testing.assert_allclose(edge, [img[0, 0], img[-1, -1]], rtol=1e-6)


def test_nan_support_propagates():
    img = np.ones((10, 10))
    img[5, 5] = np.nan
    assert np.isnan(sample(img, [5.7], [5.7], "bl"))[0]
    assert np.isfinite(sample(img, [2.5], [2.5], "cr"))[0]
    assert sample(img, [2.5], [2.5], "cr")[0] == pytest.approx(1.0)


def test_unknown_kernel_names_the_field():
    with pytest.raises(InvalidOptionError, match=r"--kernel: unknown interpolation kernel 'lanczos'.*\['bl', 'cr', 'cs', 'nn'\]"):
        get_kernel("lanczos", field="--kernel")
    assert get_kernel("CR") is KERNELS["cr"]
