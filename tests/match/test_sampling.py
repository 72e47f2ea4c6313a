"""The matching sweep's image interpolation (tiledsm.match.sampling) against
two oracles: Keys' kernel summed in float64 by numpy, and OpenCV's
INTER_CUBIC (a = -0.75, float weights for float32 images) at positions
OpenCV's remap represents exactly."""

import cv2
import numpy as np

from tiledsm.match.sampling import CUBIC_A, cubic_weights, interpolate


def _keys64(d: np.ndarray) -> np.ndarray:
    """Keys' kernel, float64, from its piecewise definition."""
    a = CUBIC_A
    d = np.abs(d)
    near = (a + 2) * d**3 - (a + 3) * d**2 + 1
    far = a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a
    return np.where(d <= 1, near, np.where(d < 2, far, 0.0))


def _bicubic64(img: np.ndarray, y: float, x: float) -> float:
    iy, ix = int(np.floor(y)), int(np.floor(x))
    rows = np.arange(iy - 1, iy + 3)
    cols = np.arange(ix - 1, ix + 3)
    wy = _keys64(y - rows)
    wx = _keys64(x - cols)
    return float(wy @ img[np.ix_(rows, cols)].astype(np.float64) @ wx)


def _positions(rng, n, h, w):
    return rng.uniform(1.0, h - 2.0, n), rng.uniform(1.0, w - 2.0, n)


def test_cubic_weights_are_keys_kernel_in_float32():
    # positions already in float32: the oracle then sees the same fractions
    f = np.linspace(0.0, 1.0, 1001, endpoint=False).astype(np.float32).astype(np.float64)
    got = np.array([cubic_weights(v) for v in f])
    assert np.array_equal(got.astype(np.float32), got)  # float32 values
    want = _keys64(np.stack([f + 1, f, 1 - f, 2 - f], axis=1))
    # factored: a few ulps of each weight (expanded, 1e-6 near d = 2)
    np.testing.assert_allclose(got, want, rtol=2.7e-7, atol=1e-12)  # measured 2.2e-7
    # partition of unity, and exactly (0, 1, 0, 0) on a pixel
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1.6e-7)  # measured 1.35e-7
    assert cubic_weights(0.0) == (0.0, 1.0, 0.0, 0.0)


def test_bicubic_matches_float64_keys_sum():
    rng = np.random.default_rng(3)
    img = (rng.random((40, 50)) * 4000).astype(np.float32)
    ys, xs = _positions(rng, 2000, *img.shape)
    got = np.array([interpolate(img, y, x, True, *img.shape) for y, x in zip(ys, xs)])
    want = np.array([_bicubic64(img, y, x) for y, x in zip(ys, xs)])
    # float32 weights and sums of 16 products of samples up to 4000
    err = np.abs(got - want)
    # (measured: at most 9.3e-4, median 1.0e-4; ulp of 4000: 2.4e-4)
    assert err.max() < 1.15e-3, err.max()
    assert np.median(err) < 1.2e-4, np.median(err)


def test_bicubic_matches_opencv_inter_cubic():
    rng = np.random.default_rng(5)
    img = (rng.random((30, 35)) * 255).astype(np.float32)
    # multiples of 1/32 px: OpenCV's remap table holds exactly these fractions
    ys = np.round(rng.uniform(1.0, img.shape[0] - 2.0, 500) * 32) / 32
    xs = np.round(rng.uniform(1.0, img.shape[1] - 2.0, 500) * 32) / 32
    got = np.array([interpolate(img, y, x, True, *img.shape) for y, x in zip(ys, xs)])
    cv = cv2.remap(img, xs.astype(np.float32)[None, :], ys.astype(np.float32)[None, :], cv2.INTER_CUBIC,
                   borderMode=cv2.BORDER_REPLICATE)[0]
    # (measured: 3.05e-5 at most, one float32 ulp at 128-255: both sums
    # float32, in other orders)
    np.testing.assert_allclose(got, cv, rtol=0, atol=3.7e-5)


def test_bicubic_nan_where_support_leaves_window_or_touches_nodata():
    img = np.ones((10, 10), np.float32)
    img[5, 5] = np.nan
    assert np.isnan(interpolate(img, 0.5, 4.0, True, 10, 10))  # row 0 - 1 outside
    assert np.isnan(interpolate(img, 4.0, 8.2, True, 10, 10))  # column 8 + 2 outside
    assert np.isnan(interpolate(img, 4.2, 4.2, True, 10, 10))  # 4 x 4 support holds [5, 5]
    assert abs(interpolate(img, 2.2, 2.7, True, 10, 10) - 1.0) < 1e-6
