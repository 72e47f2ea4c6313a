"""DSM metrics against a reference streamed chunk by chunk (dask-backed
inputs) against the exact in-memory statistics, and a reference brought
onto a DSM's grid lazily against rioxarray's whole-array reprojection."""

import numpy as np
import pytest
import rasterio
import rioxarray  # noqa: F401
import xarray as xr
from rasterio.enums import Resampling

from tiledsm.geometry.grid import GroundGrid
from tiledsm.workflows.common import dsm_metrics, reference_on_grid

GRID = GroundGrid("EPSG:32631", 500_000.0, 4_900_000.0, 0.5, 150, 170)


def _on_grid(values, grid=GRID):
    a = xr.DataArray(values, dims=("y", "x"), coords={"y": grid.y, "x": grid.x})
    return a.rio.write_crs(grid.crs).rio.write_transform(grid.transform)


def _scene(seed=0):
    rng = np.random.default_rng(seed)
    ref = 300 + rng.normal(0, 5, GRID.shape)
    ref[:10, :20] = np.nan
    err = rng.normal(0.1, 0.3, GRID.shape) + (rng.random(GRID.shape) < 0.02) * rng.normal(0, 20, GRID.shape)
    dsm = (ref + err).astype(np.float32)
    dsm[rng.random(GRID.shape) < 0.1] = np.nan
    return dsm, ref.astype(np.float32), rng.random(GRID.shape) < 0.7


@pytest.mark.parametrize("chunks", [37, 64])
def test_dsm_metrics_streamed_match_exact(chunks):
    dsm, ref, mask = _scene()
    exact = dsm_metrics(_on_grid(dsm), _on_grid(ref), mask)
    lazy = dsm_metrics(_on_grid(dsm).chunk(chunks), _on_grid(ref), _on_grid(mask))
    d = dsm.astype(np.float64) - ref
    bin_width = (np.nanmax(d[mask]) - np.nanmin(d[mask])) / 2**18
    assert set(lazy) == set(exact)
    for key in ("count", "cells"):
        assert lazy[key] == exact[key]
    for key in ("completeness", "mean", "std", "rmse", "mae", "min", "max", "mre"):
        assert lazy[key] == pytest.approx(exact[key], rel=1e-9, abs=1e-12), key
    # the stated bounds: the median within one bin, the NMAD within 1.4826 * 1.5 bins
    assert abs(lazy["median"] - exact["median"]) <= bin_width
    assert abs(lazy["nmad"] - exact["nmad"]) <= 1.4826 * 1.5 * bin_width
    assert bin_width < 1e-3  # the range is +-~80 m here: sub-mm bins


def test_dsm_metrics_streamed_without_mask():
    dsm, ref, _ = _scene(1)
    exact = dsm_metrics(_on_grid(dsm), _on_grid(ref))
    lazy = dsm_metrics(_on_grid(dsm).chunk(50), _on_grid(ref).chunk(50))
    assert (lazy["count"], lazy["cells"]) == (exact["count"], exact["cells"]) == (exact["count"], int(np.isfinite(ref).sum()))
    assert lazy["rmse"] == pytest.approx(exact["rmse"], rel=1e-9)


def _write(path, values, transform, crs="EPSG:32631"):
    with rasterio.open(path, "w", driver="GTiff", width=values.shape[1], height=values.shape[0], count=1,
                       dtype="float32", crs=crs, transform=transform, nodata=-9999.0) as ds:
        ds.write(np.where(np.isfinite(values), values, -9999.0).astype(np.float32), 1)


@pytest.mark.parametrize("resampling", ["bilinear", "nearest"])
def test_reference_on_grid_is_lazy_and_matches_rioxarray(tmp_path, resampling):
    """A coarser reference (1.3 m cells, offset by a fraction of a cell,
    with holes) onto the DSM's 0.5 m grid: chunk by chunk the same cells as
    rioxarray's reproject_match of the whole raster."""
    from affine import Affine

    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:80, 0:90]
    coarse = (300 + 10 * np.sin(xx / 9.0) + 5 * np.cos(yy / 7.0) + rng.normal(0, 0.1, xx.shape)).astype(np.float32)
    coarse[30:34, 40:45] = np.nan
    path = tmp_path / "ref.tif"
    _write(path, coarse, Affine(1.3, 0, GRID.x0 - 7.7, 0, -1.3, GRID.y0 + 9.1))
    like = _on_grid(np.zeros(GRID.shape, np.float32)).chunk(48)
    got = reference_on_grid(path, like, resampling)
    assert got.chunks == like.chunks and got.shape == like.shape  # lazy, in like's chunks
    ref = rioxarray.open_rasterio(path, masked=True).squeeze("band", drop=True)
    expected = ref.rio.reproject_match(like, resampling=Resampling[resampling]).values
    values = got.values
    assert np.array_equal(np.isnan(values), np.isnan(expected))
    ok = np.isfinite(expected)
    assert ok.mean() > 0.5
    assert np.abs(values[ok] - expected[ok]).max() < 1e-3


def test_reference_on_grid_same_grid_is_sliced(tmp_path):
    dsm, ref, _ = _scene(3)
    path = tmp_path / "same.tif"
    _write(path, ref, GRID.transform)
    got = reference_on_grid(path, _on_grid(dsm).chunk(64))
    assert got.chunks == ((64, 64, 42), (64, 64, 22))  # 170 rows, 150 columns
    assert np.array_equal(got.values, ref, equal_nan=True)
    # in memory: one block, the same values
    assert np.array_equal(reference_on_grid(path, _on_grid(dsm)).values, ref, equal_nan=True)
