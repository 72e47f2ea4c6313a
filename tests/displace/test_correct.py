"""Frame correction on stable terrain: a plane and row stripes removed,
moving ground kept; no stable cell is a clear error."""

import numpy as np
import pytest

from tiledsm.displace.correct import CorrectionParams, NoStableCellsError, correct_component


def grid(n=60, res=4.0):
    x = 1000 + (np.arange(n) + 0.5) * res
    y = 5000 - (np.arange(n) + 0.5) * res
    return x, y


def test_plane_fitted_on_stable_cells_leaves_the_motion():
    x, y = grid()
    X, Y = np.meshgrid(x, y)
    rng = np.random.default_rng(0)
    frame = 0.3 + 1e-3 * (X - 1100) - 2e-3 * (Y - 4900)
    motion = np.where(X > 1150, 0.8, 0.0)
    v = frame + motion + rng.normal(size=X.shape) * 0.01
    stable = X < 1120
    out, rep = correct_component(v, x, y, stable)
    np.testing.assert_allclose(rep["slope_x_per_m"], 1e-3, atol=1e-4)
    np.testing.assert_allclose(rep["slope_y_per_m"], -2e-3, atol=1e-4)
    err = out - motion
    assert abs(np.median(err)) < 0.01 and 1.4826 * np.median(np.abs(err - np.median(err))) < 0.015
    assert rep["stable_after"]["nmad"] < 0.015 < rep["stable_before"]["nmad"]


def test_row_stripes_are_removed():
    x, y = grid()
    rng = np.random.default_rng(1)
    stripes = 0.05 * np.sin(np.arange(y.size) / 3.0)[:, None]
    v = stripes + rng.normal(size=(y.size, x.size)) * 0.005
    stable = np.ones(v.shape, bool)
    plain, _ = correct_component(v, x, y, stable)
    out, rep = correct_component(v, x, y, stable, CorrectionParams(stripes="rows", stripe_rows=1))
    assert np.std(out) < 0.4 * np.std(plain)
    assert rep["stripes"]["std"] == pytest.approx(np.std(stripes), rel=0.2)


def test_no_stable_cell_left_is_a_clear_error():
    x, y = grid()
    v = np.zeros((y.size, x.size))
    v[:, :30] = np.nan  # no texture where the terrain is stable
    stable = np.zeros(v.shape, bool)
    stable[:, :30] = True
    with pytest.raises(NoStableCellsError, match="dE: 0 stable cell"):
        correct_component(v, x, y, stable, name="dE")
