"""dU read at the displaced position: a slope that moved sideways is not uplift."""

import dask.array as da
import numpy as np
import pytest

from tiledsm.displace.vertical import vertical_displacement

RES, STEP, N = 0.5, 8, 256


def test_moved_slope_reads_its_true_uplift_not_the_naive_difference():
    x = (np.arange(N) + 0.5) * RES
    pre = np.tile(0.2 * x, (N, 1)) + 100  # slope 0.2 rising east
    post = np.tile(0.2 * (x - 1.5), (N, 1)) + 100 + 0.7  # moved 1.5 m east, raised 0.7 m
    dE = np.full((N // STEP, N // STEP), 1.5)
    dN = np.zeros_like(dE)
    out = vertical_displacement(da.from_array(pre, 64), da.from_array(post, 64), da.from_array(dE, 8),
                                da.from_array(dN, 8), step=STEP, res=RES).compute()
    assert np.nanmax(np.abs(out[0] - 0.7)) < 1e-4
    assert np.isfinite(out[0]).all()
    assert np.median(post - pre) == pytest.approx(0.7 - 0.2 * 1.5)  # what dh alone would say
    assert np.nanmedian(out[1]) == pytest.approx(np.degrees(np.arctan(0.2)), abs=0.01)


def test_north_motion_and_chunking():
    y = (np.arange(N) + 0.5) * RES  # row index * res, rows go south
    pre = np.tile((0.1 * y)[:, None], (1, N))  # heights grow southward
    # moved 1.0 m north: the point at row-distance y is now at y - 1.0
    post = np.tile((0.1 * (y + 1.0))[:, None], (1, N)) + 0.25
    dN = np.full((N // STEP, N // STEP), 1.0)
    dE = np.zeros_like(dN)
    a = vertical_displacement(da.from_array(pre, 64), da.from_array(post, 64), da.from_array(dE, 8),
                              da.from_array(dN, 8), step=STEP, res=RES).compute()
    b = vertical_displacement(da.from_array(pre, 128), da.from_array(post, 128), da.from_array(dE, 16),
                              da.from_array(dN, 16), step=STEP, res=RES).compute()
    assert np.nanmax(np.abs(a[0] - 0.25)) < 1e-4
    np.testing.assert_array_equal(a, b)
