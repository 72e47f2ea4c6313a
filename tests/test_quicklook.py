"""Quick-looks: the hillshade against the analytic Lambertian value of
planes, and the PNG files by their header."""

from __future__ import annotations

import math
import os
import struct

import dask.array as dsa
import numpy as np
import pytest
import xarray as xr

from tiledsm.geometry.grid import GroundGrid
from tiledsm.quicklook import hillshade, quicklook


def _plane(a: float, b: float, dy: float, dx: float, shape=(40, 50)) -> np.ndarray:
    """z = a * east + b * north on a north-up grid (rows run south)."""
    i, j = np.mgrid[: shape[0], : shape[1]]
    return a * (j * dx) + b * (-(i * dy))


def _lambert(a, b, az, alt):
    n = np.array([-a, -b, 1.0]) / math.sqrt(1 + a * a + b * b)
    az, alt = math.radians(az), math.radians(alt)
    light = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
    return max(0.0, float(n @ light))


@pytest.mark.parametrize(
    "a, b, az, alt, dy, dx",
    [
        (0.0, 0.0, 315, 45, 1.0, 1.0),
        (0.3, -0.2, 315, 45, 0.5, 0.5),
        (-1.0, 0.5, 90, 30, 2.0, 1.0),
        (0.7, 0.7, 45, 60, 1.0, 3.0),
        (2.0, 0.0, 270, 20, 1.0, 1.0),  # steep slope facing away from the light: fully dark
    ],
)
def test_hillshade_of_plane_is_lambertian(a, b, az, alt, dy, dx):
    z = _plane(a, b, dy, dx)
    s = hillshade(z, (dy, dx), azimuth=az, altitude=alt)
    np.testing.assert_allclose(s, _lambert(a, b, az, alt), rtol=0, atol=1e-12)


def test_hillshade_orientation_and_nan():
    # a slope rising to the south-east faces north-west: lit by a NW light
    z = _plane(0.5, -0.5, 1.0, 1.0)
    assert hillshade(z)[5, 5] > hillshade(-z)[5, 5]
    z[10, 10] = np.nan
    s = hillshade(z)
    assert np.isnan(s[10, 10]) and np.isnan(s[9, 10]) and np.isnan(s[10, 11])
    assert np.isfinite(s).sum() == s.size - 5


def _png_size(path) -> tuple[int, int]:
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


def _dsm() -> xr.DataArray:
    g = GroundGrid("EPSG:32631", 0.0, 1000.0, 0.5, width=300, height=200, chunk=64)
    yy, xx = np.meshgrid(g.y, g.x, indexing="ij")
    z = 100 + 5 * np.sin(xx / 15.0) * np.cos(yy / 11.0)
    z[50:60, 50:80] = np.nan
    return xr.DataArray(dsa.from_array(z.astype(np.float32), chunks=64), dims=("y", "x"), coords=g.coords())


def test_quicklook_height_png(tmp_path):
    p = quicklook(_dsm(), tmp_path / "dsm.png", title="DSM", figsize=(6, 4), dpi=50)
    assert _png_size(p) == (300, 200)
    assert os.listdir(tmp_path) == ["dsm.png"]
    p = quicklook(_dsm(), tmp_path / "dsm2.png")  # default size follows the aspect
    w, h = _png_size(p)
    assert w == 800 and 400 <= h <= 700


def test_quicklook_difference_png_and_downsampling(tmp_path):
    dsm = _dsm()
    diff = dsm - dsm.mean() + 0.1
    p = quicklook(diff, tmp_path / "d.png", kind="difference", dsm=dsm, figsize=(5, 5), dpi=40, max_size=64)
    assert _png_size(p) == (200, 200)
    p = quicklook(diff, tmp_path / "d2.png", kind="difference", figsize=(5, 5), dpi=40)
    assert _png_size(p) == (200, 200)
    with pytest.raises(ValueError, match="kind must be one of"):
        quicklook(diff, tmp_path / "x.png", kind="slope")
    assert sorted(os.listdir(tmp_path)) == ["d.png", "d2.png"]
