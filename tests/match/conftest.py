"""Fixtures of the matching tests (scene builder in match_synthetic.py)."""

import pytest

from match_synthetic import make_scene


@pytest.fixture(scope="session")
def synthetic_scene():
    """Two-view synthetic scene (affine RPCs, GSD 0.5 m, B/H 0.4)."""
    return make_scene()
