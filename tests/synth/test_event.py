"""The displacement field of the synthetic event: both blocks moving, or
the left one still (the frame a real study measures against)."""

import numpy as np
import pytest

from tiledsm.synth.event import EventParams, displacement, evaluate_post
from tiledsm.synth.terrain import make_world


@pytest.mark.parametrize("still", ["none", "left"])
def test_blocks_move_by_their_share(still):
    ev = EventParams(fault_point=(0.0, 0.0), strike_deg=0.0, throw=2.0, slip=1.5, uplift=0.0, still=still)
    x = np.linspace(-50, 50, 101)
    y = np.linspace(-20, 20, 5)
    side, dx, dy, dz = displacement(ev, x, y)
    right, left = side, ~side  # strike north: the right block is east (x >= 0)
    assert right.any() and left.any() and (right == (x[None, :] >= 0)).all()
    r_share, l_share = {"none": (0.5, -0.5), "left": (1.0, 0.0)}[still]
    np.testing.assert_allclose(dy[right], r_share * 1.5, atol=1e-6)  # along the strike (north)
    np.testing.assert_allclose(dy[left], l_share * 1.5, atol=1e-6)
    np.testing.assert_allclose(dx, 0.0, atol=1e-6)
    np.testing.assert_allclose(dz[right], r_share * 2.0, atol=1e-6)
    np.testing.assert_allclose(dz[left], l_share * 2.0, atol=1e-6)
    # offset across the fault is the same whichever block stays
    assert dy[right].mean() - dy[left].mean() == pytest.approx(1.5, abs=1e-6)
    assert ev.max_horizontal == pytest.approx(max(abs(r_share), abs(l_share)) * 1.5)


def test_post_surface_of_a_still_block_is_the_pre_surface():
    world = make_world(seed=2)
    ev = EventParams(fault_point=(0.0, 0.0), strike_deg=30.0, throw=2.0, slip=1.5, uplift=0.0, still="left")
    x = np.linspace(-60, 60, 121)
    y = np.linspace(-60, 60, 121)
    h_post, _, _, dx, dy, dz = evaluate_post(world, ev, x, y)
    h_pre, _, _ = world.evaluate(x, y)
    side, *_ = displacement(ev, x, y)
    np.testing.assert_array_equal(h_post[~side], h_pre[~side])
    # the right block: the pre surface moved by the full slip, raised by the throw
    s = 1.5 * ev.strike
    h_shift, _, _ = world.evaluate(x - s[0], y - s[1])
    np.testing.assert_allclose(h_post[side], h_shift[side] + 2.0, atol=1e-5)


def test_unknown_still_side_is_refused():
    with pytest.raises(ValueError, match="still: expected one of"):
        EventParams(still="right")
