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


def test_reference_accuracy_finds_where_the_dsm_lies(synth):
    """A DSM whose content sits 3 m east and 2 m south of the reference
    (the same analytic terrain sampled at shifted points, no resampling in
    the truth): the co-registered statistics give that offset and the
    residual of the interpolation only; the plain ones are untouched."""
    shape = (160, 180)
    ref = synth.terrain(*synth.centres(shape))
    # DSM(x, y) = ref(x - 3, y + 2): each cell holds the terrain 3 m west and 2 m north of its centre
    dsm = synth.terrain(*synth.centres(shape, drow=-2.0 / synth.RES, dcol=-3.0 / synth.RES))
    dsm[40:50, 60:75] = np.nan  # a hole
    stats, _ = reference_accuracy(synth.to_dataarray(dsm).chunk(64), synth.to_dataarray(ref, "ref"), chunks=64,
                                  coregister=True)
    c = stats["coregistered"]
    # measured: 3.021 / -2.015 m (the bilinear move's bias, 0.2 % of a 10 m cell)
    assert c["offset_east_m"] == pytest.approx(3.0, abs=0.03)
    assert c["offset_north_m"] == pytest.approx(-2.0, abs=0.03)
    assert c["converged"] and "completeness" not in c
    assert stats["nmad"] > 1.0 and c["nmad"] < 0.025  # measured 1.017 and 0.019 m
    plain, _ = reference_accuracy(synth.to_dataarray(dsm).chunk(64), synth.to_dataarray(ref, "ref"), chunks=64)
    assert plain == {k: v for k, v in stats.items() if k != "coregistered"}


def test_reference_accuracy_on_flat_ground_says_why_it_has_no_offset():
    """Flat ground has no slope to fit an offset on: the co-registered part
    says so and the plain statistics stand (a DSM run with --reference over
    flat ground failed after its DSM was computed)."""
    grid = GroundGrid("EPSG:32631", 500_000.0, 4_900_000.0, 0.5, 100, 100)
    flat = np.full(grid.shape, 300.0)
    noisy = flat + np.random.default_rng(0).normal(0, 0.1, grid.shape)
    stats, _ = reference_accuracy(_grid_array(noisy, grid), _grid_array(flat, grid), coregister=True)
    assert set(stats["coregistered"]) == {"error"} and "slope" in stats["coregistered"]["error"]
    assert stats["nmad"] == pytest.approx(0.1, abs=0.01) and stats["completeness"] == 1.0


def test_reference_accuracy_reads_the_dsm_three_times(synth):
    """With the co-registration, each block of the DSM is read once for the
    fit's windows (the whole grid when small), once for the ranges of both
    differences and once for both histograms (it was five: two passes per
    difference)."""
    from collections import Counter

    shape = (160, 180)
    ref = synth.terrain(*synth.centres(shape))
    dsm = synth.terrain(*synth.centres(shape, drow=-0.5, dcol=-0.7))
    reads: Counter = Counter()

    def read(block, block_info=None):
        reads[tuple(block_info[0]["chunk-location"])] += 1
        return block

    height = synth.to_dataarray(dsm).chunk(64)
    height = height.copy(data=height.data.map_blocks(read, dtype=height.dtype))
    stats, _ = reference_accuracy(height, synth.to_dataarray(ref, "ref"), chunks=64, coregister=True)
    assert "nmad" in stats["coregistered"]
    assert len(reads) == 9 and set(reads.values()) == {3}
