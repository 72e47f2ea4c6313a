"""Fixtures of the ortho tests: one small synthetic stereo scene per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def ortho_scene(tmp_path_factory):
    """A 256 x 256 two-view scene (B/H 0.6, buildings: occlusions) with truth."""
    from tiledsm.synth import make_scene

    return make_scene(tmp_path_factory.mktemp("ortho_scene"), size=256, gsd=0.5, bh=0.6, seed=3, chunk=128, workers=2)
