"""Chunked DSM accuracy against the exact in-memory statistics."""

import numpy as np
import pytest
import xarray as xr

from tiledsm.compare.accuracy import reference_accuracy
from tiledsm.compare.stats import difference_statistics
from tiledsm.errors import NoOverlapError
from tiledsm.geometry.grid import GroundGrid


def _grid_array(values, grid, chunks=None):
    import rioxarray  # noqa: F401

    a = xr.DataArray(values.astype(np.float32), dims=("y", "x"), coords={"y": grid.y, "x": grid.x})
    a = a.rio.write_crs(grid.crs).rio.write_transform(grid.transform)
    return a.chunk(chunks) if chunks else a


@pytest.mark.parametrize("chunks", [37, 256])
def test_reference_accuracy_matches_exact_statistics(chunks):
    rng = np.random.default_rng(0)
    grid = GroundGrid("EPSG:32631", 500_000.0, 4_900_000.0, 0.5, 150, 170)
    ref = 300 + rng.normal(0, 5, grid.shape)
    ref[:10, :20] = np.nan  # the reference has holes
    err = rng.normal(0.1, 0.3, grid.shape) + (rng.random(grid.shape) < 0.02) * rng.normal(0, 20, grid.shape)
    dsm = ref + err
    dsm[rng.random(grid.shape) < 0.1] = np.nan  # and so has the DSM
    mask = rng.random(grid.shape) < 0.7
    stats, diff = reference_accuracy(_grid_array(dsm, grid, chunks), _grid_array(ref, grid), _grid_array(mask * 1.0, grid), chunks=chunks)
    d32 = dsm.astype(np.float32).astype(np.float64) - ref.astype(np.float32)
    sel = np.isfinite(ref) & mask
    exact = difference_statistics(d32[sel], reference=ref.astype(np.float32)[sel])
    width = (np.nanmax(d32) - np.nanmin(d32)) / 2**18
    for key in ("count", "cells"):
        assert stats[key] == exact[key]
    for key in ("completeness", "mean", "std", "rmse", "mae", "min", "max", "mre"):
        assert stats[key] == pytest.approx(exact[key], rel=1e-5, abs=1e-6), key
    for key in ("median", "nmad"):
        assert stats[key] == pytest.approx(exact[key], abs=2 * width), key
    assert diff.shape == grid.shape and np.isnan(diff.values[:10, :20]).all()
    assert diff.attrs["window"] == (0, grid.height, 0, grid.width)


def test_reference_accuracy_without_overlap():
    grid = GroundGrid("EPSG:32631", 500_000.0, 4_900_000.0, 0.5, 20, 20)
    far = GroundGrid("EPSG:32631", 600_000.0, 4_900_000.0, 0.5, 20, 20)
    with pytest.raises(NoOverlapError):
        reference_accuracy(_grid_array(np.zeros(grid.shape), grid), _grid_array(np.zeros(far.shape), far))
