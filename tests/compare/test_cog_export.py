"""``dh.tif`` of ``tiledsm compare``, through the command: a COG (DEFLATE level 1,
floating-point predictor) holding ``dh.zarr``'s values, whose overviews (averaged
while the rows stream, :mod:`tiledsm.io.overviews`) are the ones GDAL's ``COG``
driver computes from the same grid (the oracle: ``write_cog`` letting GDAL
average them), NaN holes included."""

from __future__ import annotations

import os

import numpy as np
import rasterio

from tests.compare.conftest import centres, terrain, write_tif
from tiledsm.cli import main
from tiledsm.io import open_product, write_cog

N = 1024  # one overview level (tiles of 512), 16 chunks of 256


def test_dh_tif_holds_dh_zarr_and_gdals_overviews(tmp_path):
    ref = terrain(*centres((N, N)))
    other = terrain(*centres((N, N), 1.3, -0.7)) + 2.0
    other[300:340, 500:700] = np.nan  # a hole: NaN cells in dh, partly NaN 2 x 2 groups
    refp, othp = write_tif(tmp_path / "ref.tif", ref), write_tif(tmp_path / "other.tif", other)
    out = tmp_path / "out"
    assert main(["compare", str(refp), str(othp), "--out", str(out), "--chunks", "256", "--no-progress"]) == 0
    assert not [p for p in os.listdir(out) if p.startswith(".")]  # no source, VRT or level file left

    dh = open_product(out / "dh.zarr")["dh"]
    with rasterio.open(out / "dh.tif") as cog:
        assert cog.tags(ns="IMAGE_STRUCTURE") == {"LAYOUT": "COG", "COMPRESSION": "DEFLATE", "INTERLEAVE": "BAND",
                                                  "PREDICTOR": "3"}
        assert cog.overviews(1) == [2] and cog.block_shapes == [(512, 512)]
        full = cog.read(1)
    np.testing.assert_array_equal(full, dh.values)
    assert np.isnan(full).any()
    gdal = write_cog(dh, tmp_path / "gdal.tif", overviews="gdal")  # GDAL's COG driver averages them
    with rasterio.open(out / "dh.tif", overview_level=0) as ours, rasterio.open(gdal, overview_level=0) as want:
        got, expect = ours.read(1), want.read(1)
    assert got.shape == (N // 2, N // 2) and np.isnan(expect).any()
    np.testing.assert_array_equal(got, expect)
