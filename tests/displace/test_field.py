"""The tiled displacement field of two orthos: units and signs, tile
invariance, grids that do not match."""

import numpy as np
import pytest
from affine import Affine
from shift_cases import fourier_shift, ortho, texture

from tiledsm.displace import CorrelationParams, correlate_orthos
from tiledsm.errors import GridError


def test_metres_east_north_and_the_coarse_grid():
    base = texture(n=256)
    post = fourier_shift(base, 1.3, -2.2)  # 1.3 rows down (south), 2.2 columns left (west)
    f = correlate_orthos(ortho(base), ortho(post), CorrelationParams(step=8), chunk=128).compute()
    assert f.dE.shape == (32, 32)
    assert f.rio.transform() == Affine(4.0, 0, 500000.0, 0, -4.0, 4000000.0)
    inner = f.dE.values[4:-4, 4:-4]
    assert np.nanmedian(inner) == pytest.approx(-2.2 * 0.5, abs=0.002)
    assert np.nanmedian(f.dN.values[4:-4, 4:-4]) == pytest.approx(-1.3 * 0.5, abs=0.002)
    assert np.isfinite(inner).all()


@pytest.mark.slow
def test_field_does_not_depend_on_the_chunking():
    base = texture(n=1024, seed=3)
    post = fourier_shift(base, 0.37, 1.6) + np.random.default_rng(1).normal(size=base.shape)
    a, b = ortho(base), ortho(post)
    f256 = correlate_orthos(a, b, chunk=256).compute()
    f1024 = correlate_orthos(a, b, chunk=1024).compute()
    for v in ("dE", "dN", "quality"):
        np.testing.assert_array_equal(f256[v].values, f1024[v].values)
    assert np.isfinite(f256.dE.values).mean() > 0.9


def test_orthos_on_different_grids_are_refused():
    base = texture(n=128)
    with pytest.raises(GridError, match="not on the same grid.*transform"):
        correlate_orthos(ortho(base), ortho(base, x0=500000.25))
    with pytest.raises(GridError, match="shape"):
        correlate_orthos(ortho(base), ortho(base[:120]))
    with pytest.raises(GridError, match="CRS"):
        correlate_orthos(ortho(base), ortho(base, crs="EPSG:32632"))


def test_stored_orthos_give_the_same_field_and_read_their_own_windows(tmp_path):
    """Orthos given as zarr stores: every task reads its window and halo
    itself (no task depends on another), with values identical to the
    map_overlap of the same orthos, here on a grid that is not a multiple
    of the step or the chunk (cropped edge, NaN halo past it) and holds
    nodata."""
    from tiledsm.io import write_zarr

    base = texture(n=300, seed=5)
    post = fourier_shift(base, -0.6, 2.3) + np.random.default_rng(2).normal(size=base.shape)
    post[:40, :70] = np.nan
    a, b = ortho(base[:, :290]).rename("ortho"), ortho(post[:, :290]).rename("ortho")
    write_zarr(a.chunk(100), tmp_path / "pre.zarr")
    write_zarr(b.chunk(100), tmp_path / "post.zarr")
    ref = correlate_orthos(a, b, chunk=128).compute()
    lazy = correlate_orthos(tmp_path / "pre.zarr", tmp_path / "post.zarr", chunk=128)
    graph = dict(lazy.dE.data.__dask_graph__())
    correlation = [k for k in graph if "correlate-" in str(k[0] if isinstance(k, tuple) else k)]
    assert len(correlation) == 3 * 3  # 36 x 36 cells in blocks of 16 ... and nothing feeds them
    from dask.core import get_dependencies

    assert all(not get_dependencies(graph, k) for k in correlation)
    got = lazy.compute()
    for v in ("dE", "dN", "quality", "texture"):
        np.testing.assert_array_equal(got[v].values, ref[v].values)
    assert got.rio.transform() == ref.rio.transform() and got.rio.crs == ref.rio.crs
    assert 0.5 < np.isfinite(got.dE.values).mean() < 1.0  # the nodata corner is NaN
    with pytest.raises(TypeError, match="two store paths"):
        correlate_orthos(tmp_path / "pre.zarr", b)
