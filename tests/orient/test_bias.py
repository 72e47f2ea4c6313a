"""Bias models: registry, the model's equations, model choice."""

from __future__ import annotations

import numpy as np
import pytest

from tiledsm.errors import InvalidOptionError
from tiledsm.orient.bias import MODELS, TERMS, choose_model, get_model


def test_registry_and_unknown_name():
    assert set(MODELS) == {"shift", "affine"}
    assert get_model("affine").terms == TERMS
    with pytest.raises(InvalidOptionError, match="unknown bias model 'poly'.*shift, affine"):
        get_model("poly")


def test_correction_is_the_fraser_hanley_left_hand_side():
    m = get_model("affine")
    x = np.array([1.5, 2e-3, -3e-3, -0.5, 4e-3, 1e-3])  # A0 A1 A2 B0 B1 B2
    l, s = np.array([10.0, 200.0]), np.array([30.0, 5.0])
    r, c = m.correction(x, l, s)
    np.testing.assert_allclose(r, l + 1.5 + 2e-3 * l - 3e-3 * s)
    np.testing.assert_allclose(c, s - 0.5 + 4e-3 * l + 1e-3 * s)
    # the design is the exact derivative (the model is linear in its terms)
    dr, dc = m.design(l, s)
    for k in range(6):
        e = np.zeros(6)
        e[k] = 1.0
        r1, c1 = m.correction(x + e, l, s)
        np.testing.assert_allclose(r1 - r, dr[:, k])
        np.testing.assert_allclose(c1 - c, dc[:, k])
    shift = get_model("shift")
    a, b = shift.full([2.0, -1.0])
    assert a.tolist() == [2.0, 0.0, 0.0] and b.tolist() == [-1.0, 0.0, 0.0]


@pytest.mark.parametrize("n_gcp,n_tie,name", [(0, 0, "shift"), (2, 5, "shift"), (3, 0, "affine"), (0, 30, "affine"),
                                              (1, 29, "shift")])
def test_choice_by_point_count(n_gcp, n_tie, name):
    assert choose_model(n_gcp, n_tie).name == name
