"""Image-space matcher on Middlebury Cones (Scharstein & Szeliski, CVPR 2003):
validates the ZNCC cost + 8-path aggregation core against ground truth."""

import warnings

import numpy as np
import pytest

from stereo import StereoParams, cost_volume, disparity, fill_occlusions


def _read(shared_data, name):
    import rasterio

    path = shared_data("pandora_middlebury_cones", name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            return ds.read(1)


@pytest.mark.realdata
@pytest.mark.parametrize("window, max_bad", [(5, 0.13), (3, 0.11)])
def test_cones_bad_pixel_rate(shared_data, window, max_bad):
    left = _read(shared_data, "Cones_LEFT.tif").astype(np.float32)
    right = _read(shared_data, "Cones_RIGHT.tif").astype(np.float32)
    gt = _read(shared_data, "Cones_LEFT_GT.tif")
    has_gt = gt > 0
    disp, _ = disparity(left, right, 0, 63, StereoParams(window=window))
    filled = fill_occlusions(disp)
    err = np.abs(filled - gt)[has_gt]
    bad = float(np.mean(~(err <= 1.0)))  # NaN counts as bad
    valid = np.isfinite(disp) & has_gt
    bad_valid = float(np.mean(np.abs(disp - gt)[valid] > 1.0))
    # measured: window 5 -> 11.7 % (MAE 0.82 px), window 3 -> 9.3 % (MAE 0.72 px); issue bound 15 %
    assert bad <= max_bad, f"bad-pixel rate {bad:.3f}"
    assert np.nanmean(err) < 1.0
    # cells kept by the left-right check are much better than the filled ones
    assert valid.sum() / has_gt.sum() > 0.8 and bad_valid < 0.07


def test_cost_volume_shift_sign():
    rng = np.random.default_rng(0)
    left = rng.random((30, 60)).astype(np.float32)
    right = np.roll(left, -7, axis=1)  # x_right = x_left - 7
    vol = cost_volume(left, right, 0, 12, 5)
    best = np.nanargmin(np.where(np.isnan(vol), 9, vol)[5:-5, 15:-5], axis=2)
    assert np.all(best == 7)


def test_match_tiepoints_downsamples_large_images_and_returns_full_pixels():
    """Images above ``max_size`` are detected on an area-downsampled copy
    (this path once imported a function that did not exist); the points come
    back in full-image pixels: a known 7.5 x 4.25 px shift is recovered."""
    import cv2

    from tiledsm.match.tiepoints import match_tiepoints

    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.random((700, 700)).astype(np.float32), (0, 0), 2.0)
    m = np.float32([[1, 0, 7.5], [0, 1, 4.25]])
    moved = cv2.warpAffine(base, m, (700, 700), flags=cv2.INTER_CUBIC)
    p1, p2 = match_tiepoints(base[20:-20, 20:-20], moved[20:-20, 20:-20], max_size=300)
    assert len(p1) > 50
    d = np.median(p2 - p1, axis=0)  # (row, col)
    np.testing.assert_allclose(d, [4.25, 7.5], atol=0.3)
