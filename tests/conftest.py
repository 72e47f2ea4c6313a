"""Shared fixtures.

Real data lives in ``../shared/data`` (beside the repository, never copied
into it). Tests that need it use :func:`shared_data`: when the folder is
absent they skip with the reason, except under ``CI=true``, where its absence
is a failure.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(
    os.environ.get("TILEDSM_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data")
)


def require_shared(*parts: str) -> Path:
    """Path to ``../shared/data/<parts>``; skip (or fail under CI) when absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        msg = f"shared test data not found: {path} (expected ../shared/data beside the repository)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + " -- required under CI=true")
        pytest.skip(msg)
    return path


@pytest.fixture
def shared_data():
    """Callable fixture: ``shared_data("s2p_pair", "input_pair", "img_01.tif")``."""
    return require_shared
