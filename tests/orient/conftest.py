"""Fixtures of the orientation tests: synthetic cameras with injected
biases (no rendering) and a small rendered scene."""

from __future__ import annotations

import pytest

from simulate import inject_bias, pushbroom_rpcs

from orient_cases import BIASES, H_RANGE, SIZE  # noqa: E402


@pytest.fixture(scope="session")
def cameras3():
    """(true RPCs, biased RPCs) of 3 synthetic pushbroom views."""
    true = pushbroom_rpcs(3, SIZE, h_range=H_RANGE)
    biased = [inject_bias(r, a, b, (SIZE, SIZE), H_RANGE) for r, (a, b) in zip(true, BIASES)]
    return true, biased


@pytest.fixture(scope="session")
def scene2(tmp_path_factory):
    """A rendered 512-px 2-view scene with 1 px shifts injected into
    biased copies, and the true cameras."""
    from tiledsm.io.cameras import find_camera
    from simulate import biased_copies
    from tiledsm.synth import make_scene

    root = tmp_path_factory.mktemp("orient_scene")
    info = make_scene(root / "scene", size=512, views=2, seed=4, chunk=256, workers=1)
    true = [find_camera(p)[0] for p in info.views]
    h = (true[0].height_off - true[0].height_scale, true[0].height_off + true[0].height_scale)
    biased = biased_copies(info.views, true, BIASES[:2], root / "biased", h)
    return info, true, biased, h, root
