"""Fixtures for the synthetic scene tests: one small scene per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """A 192 x 192, 3-view scene with the post-event version, in 64-pixel tiles."""
    from tiledsm.synth import make_scene

    out = tmp_path_factory.mktemp("synth_scene")
    return make_scene(out, size=192, gsd=0.5, bh=0.4, seed=3, views=3, event=True, chunk=64, workers=2)
