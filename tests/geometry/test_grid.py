"""Ground grids: checked against rasterio's transform helpers, dask's chunk
normalisation, pyproj's UTM database and a real raster (s2p reference DSM)."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import rasterio.transform as rt
from dask.array.core import normalize_chunks
from pyproj import CRS
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from tests.conftest import require_shared
from tiledsm.io.grids import grid_array
from tiledsm.errors import GridError, InputFileError
from tiledsm.geometry import RPC
from tiledsm.geometry.footprint import ground_polygon
from tiledsm.geometry.footprint import grid_for_footprint
from tiledsm.geometry.grid import GroundGrid, utm_crs
from tiledsm.io.grids import grid_like


def _grid() -> GroundGrid:
    return GroundGrid("EPSG:32631", 500_000.0, 4_650_000.0, 2.0, width=1000, height=700, chunk=256)


def test_transform_coords_bounds_match_rasterio():
    g = _grid()
    assert g.transform == rt.from_origin(500_000.0, 4_650_000.0, 2.0, 2.0)
    assert g.shape == (700, 1000)
    assert g.bounds == rt.array_bounds(700, 1000, g.transform)
    # cell centres: rasterio.transform.xy with offset="center"
    xs, _ = rt.xy(g.transform, np.zeros(1000, int), np.arange(1000), offset="center")
    _, ys = rt.xy(g.transform, np.arange(700), np.zeros(700, int), offset="center")
    np.testing.assert_allclose(g.x, xs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(g.y, ys, rtol=0, atol=1e-9)
    assert g.coords()["x"] is not None and len(g.coords()["y"]) == 700


def test_chunks_and_blocks():
    g = _grid()
    assert g.chunks == normalize_chunks((256, 256), (700, 1000))
    assert g.numblocks == (3, 4)
    wins = dict(g.blocks())
    assert wins[(2, 3)] == (512, 700, 768, 1000)
    covered = np.zeros(g.shape, int)
    for r0, r1, c0, c1 in wins.values():
        covered[r0:r1, c0:c1] += 1
    assert np.all(covered == 1)
    with pytest.raises(GridError, match="block"):
        g.block_window(3, 0)


def test_subgrid_is_a_slice_of_the_parent():
    g = _grid()
    s = g.subgrid(100, 300, 250, 260)
    assert s.shape == (200, 10)
    np.testing.assert_array_equal(s.x, g.x[250:260])
    np.testing.assert_array_equal(s.y, g.y[100:300])
    assert s.crs == g.crs and s.resolution == g.resolution and s.chunk == g.chunk
    # halo beyond the parent is allowed, and extends the lattice
    h = g.window(-5, 10, -5, 10)
    np.testing.assert_allclose(h.x[5:], g.x[:10])
    np.testing.assert_allclose(h.y[:5], g.y[0] + 2.0 * np.arange(5, 0, -1))
    with pytest.raises(GridError, match="empty window"):
        g.subgrid(10, 10, 0, 5)


def test_empty_is_lazy_and_georeferenced():
    g = _grid()
    da = grid_array(g)
    assert da.chunks == g.chunks
    assert da.rio.crs == CRS.from_epsg(32631)
    assert da.rio.transform() == g.transform
    assert da.dtype == np.float32


def test_from_bounds_snaps_outward():
    g = GroundGrid.from_bounds("EPSG:32631", (1000.3, 2000.0, 1009.9, 2010.1), 2.0, chunk=4)
    assert (g.x0, g.y0, g.width, g.height) == (1000.0, 2012.0, 5, 6)
    assert g.bounds == (1000.0, 2000.0, 1010.0, 2012.0)
    # already on the lattice (with float noise): not pushed out
    g = GroundGrid.from_bounds("EPSG:32631", (0.1 * 3, 0.0, 0.3 + 0.1 * 7, 0.5), 0.1)
    assert (g.width, g.height) == (7, 5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(resolution=0.0), "resolution"),
        (dict(resolution=-1.0), "resolution"),
        (dict(resolution=float("nan")), "resolution"),
        (dict(width=0), "width"),
        (dict(chunk=0), "chunk"),
        (dict(crs="EPSG:999999"), "unknown CRS"),
        (dict(crs="EPSG:4326"), "geographic"),
    ],
)
def test_invalid_grids_raise(kwargs, match):
    args = dict(crs="EPSG:32631", x0=0.0, y0=0.0, resolution=1.0, width=10, height=10, chunk=4)
    args.update(kwargs)
    with pytest.raises(GridError, match=match):
        GroundGrid(**args)


def test_from_bounds_rejects_empty_or_bad_resolution():
    with pytest.raises(GridError, match="empty bounds"):
        GroundGrid.from_bounds("EPSG:32631", (10, 0, 10, 5), 1.0)
    with pytest.raises(GridError, match="empty bounds"):
        GroundGrid.from_bounds("EPSG:32631", (0, 5, 10, 0), 1.0)
    with pytest.raises(GridError, match="resolution"):
        GroundGrid.from_bounds("EPSG:32631", (0, 0, 10, 5), 0)


@pytest.mark.parametrize(
    "lon, lat",
    [(55.65, -21.23), (5.195, 44.207), (-58.52, -34.55), (-179.9, 10.0), (179.9, -5.0), (0.5, 0.1), (-3.1, 51.0)],
)
def test_utm_crs_matches_pyproj_database(lon, lat):
    code = utm_crs(lon, lat)
    infos = query_utm_crs_info(
        datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat)
    )
    expected = {f"{i.auth_name}:{i.code}" for i in infos}
    assert code in expected
    assert CRS.from_user_input(code).utm_zone is not None


def test_utm_crs_edges():
    assert utm_crs(180.0, 1.0) == "EPSG:32601"  # wraps to -180
    assert utm_crs(-180.0, -1.0) == "EPSG:32701"
    assert utm_crs(55.65, -21.23) == "EPSG:32740"
    with pytest.raises(GridError):
        utm_crs(0.0, 95.0)


def test_like_real_raster_and_dataarray():
    path = require_shared("s2p_pair", "expected_output", "pair", "dsm.tif")
    g = grid_like(path, chunk=128)
    with rasterio.open(path) as src:
        assert g.transform == src.transform
        assert g.shape == (src.height, src.width)
        assert CRS.from_user_input(g.crs) == CRS.from_user_input(src.crs.to_wkt())
    import rioxarray

    da = rioxarray.open_rasterio(path, chunks={"x": 256, "y": 256}).squeeze("band", drop=True)
    g2 = grid_like(da)
    assert g2.transform == g.transform and g2.shape == g.shape and g2.chunk == 256
    np.testing.assert_allclose(g2.x, da.x.values)
    np.testing.assert_allclose(g2.y, da.y.values)


def test_like_errors():
    with pytest.raises(InputFileError, match="nonexistent.tif"):
        grid_like("/nonexistent/nonexistent.tif")
    crop = require_shared("shareloc_phr_ventoux", "left_image.tif")
    with pytest.raises(GridError, match="no CRS"):
        grid_like(crop)


def test_grid_for_footprint_covers_the_image_footprint():
    path = require_shared("s2p_pair", "input_pair", "img_01.tif")
    with rasterio.open(path) as src:
        rpc, shape = RPC.from_gdal(src.rpcs.to_gdal()), src.shape
    g = grid_for_footprint(rpc, shape, (2270.0, 2380.0), 0.5, chunk=256)
    assert g.crs == "EPSG:32740"  # same zone as s2p's reference DSM
    assert g.x0 % 0.5 == 0 and g.y0 % 0.5 == 0
    left, bottom, right, top = g.bounds
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", g.crs, always_xy=True)
    pts = np.concatenate([ground_polygon(rpc, shape, h, n_per_side=8) for h in (2270.0, 2380.0)])
    x, y = tr.transform(pts[:, 0], pts[:, 1])
    assert x.min() >= left and x.max() <= right and y.min() >= bottom and y.max() <= top
    # tight: the footprint reaches within one cell of every edge
    assert max(x.min() - left, right - x.max(), y.min() - bottom, top - y.max()) <= 0.5
