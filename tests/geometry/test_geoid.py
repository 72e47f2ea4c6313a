"""Geoid grid interpolation against PROJ (pyproj vgridshift on the same grid)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import require_shared
from tiledsm.errors import InputFileError
from tiledsm.io.geoid import ellipsoid_to_geoid, geoid_height, geoid_to_ellipsoid


@pytest.fixture(scope="module")
def gtx():
    return require_shared("shareloc_phr_ventoux", "geoid", "egm96_15.gtx")


def _proj(gtx, lon, lat, h):
    import pyproj

    t = pyproj.Transformer.from_pipeline(f"+proj=vgridshift +grids={gtx} +multiplier=1")
    return t.transform(lon, lat, h)[2]


def test_matches_proj_worldwide(gtx):
    rng = np.random.default_rng(0)
    lon = np.concatenate([rng.uniform(-180, 180, 2000), [179.99, -179.99, 180.0, -180.0]])
    lat = np.concatenate([rng.uniform(-89.5, 89.5, 2000), [10.0, 10.0, -45.0, -45.0]])
    h = rng.uniform(-100, 4000, lon.size)
    want = _proj(gtx, lon, lat, h)
    got = geoid_to_ellipsoid(lon, lat, h, gtx)
    np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_allclose(ellipsoid_to_geoid(lon, lat, got, gtx), h, atol=1e-9)


def test_mont_ventoux_about_51_m(gtx):
    n = geoid_height(5.195, 44.207, gtx)
    assert 50.0 < n < 52.0
    assert geoid_height([[5.195]], [[44.207]], gtx).shape == (1, 1)


def test_missing_grid(tmp_path):
    with pytest.raises(InputFileError, match="nope.gtx"):
        geoid_height(0.0, 0.0, tmp_path / "nope.gtx")
