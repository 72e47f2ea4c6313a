"""Synthetic DSMs with known truth for the compare tests.

Terrain is an analytic sum of plane waves (wavelengths 0.5-3 km, slopes up to
~25 deg, every aspect), so a DSM sampled at shifted coordinates is the exact
misregistered copy (no resampling in the truth).
"""

from __future__ import annotations

import numpy as np
import pytest

RES = 10.0  # m per cell
X0, Y0 = 500_000.0, 4_400_000.0  # UTM 32N origin (west, north edges)
CRS = "EPSG:32632"

_rng = np.random.default_rng(42)
_K = 7
_LAM = _rng.uniform(500.0, 3000.0, _K)
_THETA = _rng.uniform(0.0, np.pi, _K)
_PHI = _rng.uniform(0.0, 2 * np.pi, _K)
_AMP = 0.035 * _LAM


def terrain(x, y):
    """Heights (m) at map coordinates (m)."""
    z = 800.0 + 0.01 * (x - X0) - 0.02 * (y - Y0)
    for lam, th, ph, a in zip(_LAM, _THETA, _PHI, _AMP):
        z = z + a * np.sin(2 * np.pi * ((x - X0) * np.cos(th) + (y - Y0) * np.sin(th)) / lam + ph)
    return z


def centres(shape, drow=0.0, dcol=0.0):
    """Map coordinates of cell centres of a grid, sampled ``(drow, dcol)`` cells further."""
    r = np.arange(shape[0])[:, None] + 0.5 + drow
    c = np.arange(shape[1])[None, :] + 0.5 + dcol
    return X0 + RES * c, Y0 - RES * r


def to_dataarray(z, name="dsm"):
    import rioxarray  # noqa: F401
    import xarray as xr
    from affine import Affine

    h, w = z.shape
    arr = xr.DataArray(
        z.astype(np.float32), dims=("y", "x"),
        coords={"y": Y0 - RES * (np.arange(h) + 0.5), "x": X0 + RES * (np.arange(w) + 0.5)},
        name=name, attrs={"source": name},
    )
    return arr.rio.write_crs(CRS).rio.write_transform(Affine(RES, 0, X0, 0, -RES, Y0))


def write_tif(path, z, crs=CRS, transform=None, nodata=None):
    import rasterio
    from affine import Affine

    transform = transform or Affine(RES, 0, X0, 0, -RES, Y0)
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype="float32", crs=crs, transform=transform, nodata=nodata) as ds:
        ds.write(z.astype(np.float32), 1)
    return path


@pytest.fixture
def synth():
    """Namespace of the helpers above."""
    import types

    return types.SimpleNamespace(terrain=terrain, centres=centres, to_dataarray=to_dataarray, write_tif=write_tif,
                                 RES=RES, X0=X0, Y0=Y0, CRS=CRS)
