"""COG overviews averaged while the grid streams (``write_cog``'s default)
against GDAL's own (the oracle: the same ``write_cog`` with ``overviews="gdal"``,
GDAL's ``COG`` driver computing them), and :func:`tiledsm.io.overviews.average_2x2` against
numpy's NaN mean."""

from __future__ import annotations

import os

import dask.array as dsa
import numpy as np
import pytest
import rasterio
import xarray as xr

from tiledsm.io import write_cog
from tiledsm.io.overviews import average_2x2, cog_overview_count, streamable_overviews


def _grid(rows: int, cols: int, chunk: int | None, seed: int = 0) -> xr.DataArray:
    """Noisy ramp (float32, m) with scattered and block NaN holes, UTM 31N, 1 m cells."""
    rng = np.random.default_rng(seed)
    h = (rng.normal(0, 3, (rows, cols)) + np.linspace(0, 100, cols)).astype(np.float32)
    h[rng.random((rows, cols)) < 0.05] = np.nan
    h[rows // 5 : rows // 3, cols // 4 : cols // 4 + 37] = np.nan
    data = dsa.from_array(h, chunks=chunk) if chunk else h
    da = xr.DataArray(data, dims=("y", "x"), coords={"y": 4.8e6 - np.arange(rows) - 0.5, "x": 6e5 + np.arange(cols) + 0.5},
                      attrs={"units": "m"})
    return da.rio.write_crs("EPSG:32631")


def _levels(path) -> list[np.ndarray]:
    with rasterio.open(path) as src:
        n = len(src.overviews(1))
        out = [src.read(1)]
    for i in range(n):
        with rasterio.open(path, overview_level=i) as src:
            out.append(src.read(1))
    return out


@pytest.mark.parametrize("rows, cols, chunk, blocksize", [
    (1024, 768, 256, 128),   # 3 levels, chunks aligned with the 8-row strips
    (1200, 1104, 100, 128),  # 4 levels (16 | 1200, 1104), chunks of 100 rows read in strips of 112
    (512, 640, None, 128),   # numpy grid: one strip
])
def test_streamed_overviews_equal_gdals_bit_for_bit(tmp_path, rows, cols, chunk, blocksize):
    da = _grid(rows, cols, chunk)
    gdal = write_cog(da, tmp_path / "gdal.tif", blocksize=blocksize, overviews="gdal")
    ours = write_cog(da, tmp_path / "ours.tif", blocksize=blocksize)
    assert sorted(os.listdir(tmp_path)) == ["gdal.tif", "ours.tif"]  # no source, VRT or level left
    with rasterio.open(gdal) as g, rasterio.open(ours) as o:
        assert o.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert o.overviews(1) == g.overviews(1) and len(g.overviews(1)) == cog_overview_count((rows, cols), blocksize)
        assert (o.crs, o.transform, o.block_shapes, o.tags()) == (g.crs, g.transform, g.block_shapes, g.tags())
        assert np.isnan(o.nodata)
    got, want = _levels(ours), _levels(gdal)
    assert len(got) == len(want) >= 3
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)  # NaN where NaN


def test_sizes_gdal_floors_fall_back_to_gdals_overviews(tmp_path):
    """1031 x 997 cells: GDAL's levels are floor(size / factor) and not 2 x 2
    means, so the overviews are left to GDAL (the same file as with ``overviews="gdal"``)."""
    da = _grid(1031, 997, 256, seed=1)
    assert not streamable_overviews((1031, 997), np.float32, cog_overview_count((1031, 997), 256))
    a = write_cog(da, tmp_path / "a.tif", blocksize=256, overviews="gdal")
    b = write_cog(da, tmp_path / "b.tif", blocksize=256)
    assert a.read_bytes() == b.read_bytes()


def test_overview_count_is_gdals():
    """GDAL's COG driver: levels until the larger side fits one tile (measured with GDAL 3.10)."""
    assert [cog_overview_count(s, 256) for s in ((1200, 1100), (1024, 1024), (600, 520), (256, 100), (1031, 997))] == [3, 2, 2, 0, 3]
    assert cog_overview_count((8192, 8192), 512) == 4


def test_average_2x2_is_the_float64_nan_mean():
    rng = np.random.default_rng(3)
    a = (rng.normal(0, 1e3, (64, 96)) * rng.choice([1e-3, 1, 1e3], (64, 96))).astype(np.float32)
    a[rng.random(a.shape) < 0.3] = np.nan
    a[:2, :2] = np.nan  # a group with no value
    v = a.astype(np.float64).reshape(32, 2, 48, 2)
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):
        want = np.nanmean(v, axis=(1, 3)).astype(np.float32)
    got = average_2x2(a)
    assert got.dtype == np.float32 and np.isnan(got[0, 0])
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="sizes must be even"):
        average_2x2(a[:, :5])
