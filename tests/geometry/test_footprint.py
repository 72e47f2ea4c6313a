"""Footprints on a real Pleiades pair (s2p_pair): windows checked by
projecting every ground cell, polygons against GDAL's RPC transformer,
overlaps against both images, and a disjoint WorldView-3 pair."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import RPCTransformer

from tests.conftest import require_shared
from tiledsm.errors import GridError, NoOverlapError
from tiledsm.geometry import RPC
from tiledsm.geometry.footprint import (
    grid_for_footprint,
    ground_polygon,
    image_window,
    overlap_lonlat_bounds,
    overlap_polygon,
    polygon_area,
)
from tiledsm.geometry.grid import GroundGrid

H_RANGE = (2270.0, 2380.0)


def _open(*parts):
    path = require_shared(*parts)
    with rasterio.open(path) as src:
        return RPC.from_gdal(src.rpcs.to_gdal(), source=str(path)), src.shape, src.rpcs


@pytest.fixture(scope="module")
def pair():
    r1, s1, g1 = _open("s2p_pair", "input_pair", "img_01.tif")
    r2, s2, g2 = _open("s2p_pair", "input_pair", "img_02.tif")
    return r1, s1, g1, r2, s2, g2


@pytest.mark.parametrize("margin", [0, 3])
def test_window_contains_every_cell_centre(pair, margin):
    rpc, shape = pair[0], pair[1]
    full = grid_for_footprint(rpc, shape, H_RANGE, 1.0, chunk=64)  # 9 x 9 tiles of 1 m cells
    tr = Transformer.from_crs(full.crs, "EPSG:4326", always_xy=True)
    heights = np.array([H_RANGE[0], 2321.3, H_RANGE[1]])[:, None]
    n_checked = 0
    for _, (r0, r1, c0, c1) in full.blocks():
        tile = full.subgrid(r0, r1, c0, c1)
        win = image_window(rpc, tile, H_RANGE, shape, margin=margin)
        xx, yy = np.meshgrid(tile.x, tile.y)
        lon, lat = tr.transform(xx.ravel(), yy.ravel())
        rows, cols = rpc.project(lon[None], lat[None], heights)
        seen = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
        if win is None:
            assert not seen.any()
            continue
        w0, w1, v0, v1 = win
        assert 0 <= w0 < w1 <= shape[0] and 0 <= v0 < v1 <= shape[1]
        # every centre that falls in the image falls in the window (array
        # element floor(row) must be inside row0:row1)
        rs, cs = np.floor(rows[seen]), np.floor(cols[seen])
        assert rs.min() >= w0 and rs.max() < w1 and cs.min() >= v0 and cs.max() < v1
        # and the window is tight: cell centres are half a cell (1 px) inside
        # the tile edge, so the unclipped window exceeds them by <= 2 px + margin
        u0, u1, x0, x1 = image_window(rpc, tile, H_RANGE, None, margin=margin)
        assert np.floor(rows.min()) - u0 <= margin + 2 and u1 - np.floor(rows.max()) - 1 <= margin + 2
        assert np.floor(cols.min()) - x0 <= margin + 2 and x1 - np.floor(cols.max()) - 1 <= margin + 2
        n_checked += 1
    assert full.numblocks == (9, 9) and n_checked >= 49  # at least the inner 7 x 7 tiles are seen


def test_window_of_tile_outside_image_is_none(pair):
    rpc, shape = pair[0], pair[1]
    full = grid_for_footprint(rpc, shape, H_RANGE, 0.5)
    far = full.subgrid(0, 50, full.width + 200, full.width + 250)  # 100 m east of the footprint
    assert image_window(rpc, far, H_RANGE, shape) is None
    # unclipped, it lies right of the image
    r0, r1, c0, c1 = image_window(rpc, far, H_RANGE, None)
    assert c0 > shape[1] or c1 < 0 or r1 < 0 or r0 > shape[0]


def test_window_of_whole_footprint_is_whole_image(pair):
    rpc, shape = pair[0], pair[1]
    full = grid_for_footprint(rpc, shape, H_RANGE, 0.5)
    assert image_window(rpc, full, H_RANGE, shape, margin=0) == (0, shape[0], 0, shape[1])


def test_bad_height_range(pair):
    rpc, shape = pair[0], pair[1]
    g = grid_for_footprint(rpc, shape, H_RANGE, 0.5)
    with pytest.raises(GridError, match="height range"):
        image_window(rpc, g, (100.0, 0.0), shape)


def test_ground_polygon_matches_gdal(pair):
    rpc, shape, gdal_rpcs = pair[0], pair[1], pair[2]
    poly = ground_polygon(rpc, shape, 2300.0, n_per_side=4)
    rows = np.array([0, 0, 0, 0, 0, 256, 512, 768, 1024, 1024, 1024, 1024, 1024, 768, 512, 256])
    cols = np.array([0, 256, 512, 768, 1024, 1024, 1024, 1024, 1024, 768, 512, 256, 0, 0, 0, 0])
    with RPCTransformer(gdal_rpcs, RPC_PIXEL_ERROR_THRESHOLD=1e-9) as tr:
        lon, lat = tr.xy(rows, cols, zs=np.full(rows.shape, 2300.0), offset="ul")
    # 1e-9 deg ~ 0.1 mm on the ground, far below GDAL's 1e-9 px iteration tolerance
    np.testing.assert_allclose(poly[:, 0], lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(poly[:, 1], lat, rtol=0, atol=1e-9)


def test_overlap_of_real_pair(pair):
    r1, s1, _, r2, s2, _ = pair
    lo0, la0, lo1, la1 = overlap_lonlat_bounds(r1, s1, r2, s2, H_RANGE)
    for rpc, shape in ((r1, s1), (r2, s2)):
        p = np.concatenate([ground_polygon(rpc, shape, h) for h in H_RANGE])
        assert p[:, 0].min() <= lo0 < lo1 <= p[:, 0].max()
        assert p[:, 1].min() <= la0 < la1 <= p[:, 1].max()
    poly = overlap_polygon(r1, s1, r2, s2, 2320.0)
    area = polygon_area(poly)
    assert area > 0
    assert area <= abs(polygon_area(ground_polygon(r1, s1, 2320.0))) * (1 + 1e-9)
    # points inside the overlap (shrunk towards its centroid) project inside both images
    c = poly.mean(axis=0)
    pts = c + 0.98 * (poly - c)
    for rpc, shape in ((r1, s1), (r2, s2)):
        rows, cols = rpc.project(pts[:, 0], pts[:, 1], 2320.0)
        assert np.all((rows > 0) & (rows < shape[0]) & (cols > 0) & (cols < shape[1]))


def test_disjoint_worldview_crops_raise():
    r1, s1, _ = _open("rpc_models", "shareloc", "wv3_20.NTF")
    r2, s2, _ = _open("rpc_models", "shareloc", "wv3_30.NTF")
    with pytest.raises(NoOverlapError, match="wv3_20.NTF and .*wv3_30.NTF"):
        overlap_lonlat_bounds(r1, s1, r2, s2, (0.0, 200.0))
    with pytest.raises(NoOverlapError, match="no common ground"):
        overlap_polygon(r1, s1, r2, s2, 50.0)


def test_overlap_polygon_of_identical_images_is_the_footprint(pair):
    r1, s1 = pair[0], pair[1]
    poly = overlap_polygon(r1, s1, r1, s1, 2300.0)
    fp = ground_polygon(r1, s1, 2300.0)
    np.testing.assert_allclose(abs(polygon_area(poly)), abs(polygon_area(fp)), rtol=1e-9)
