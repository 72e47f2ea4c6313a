"""Common grid: exact slicing on a shared grid, GDAL-checked resampling otherwise, no-overlap errors."""

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.warp import Resampling, reproject

from tiledsm.compare import align_dsms, open_dsm
from tiledsm.errors import InputFileError, NoOverlapError


def test_same_grid_is_sliced_not_resampled(synth, tmp_path):
    z = synth.terrain(*synth.centres((60, 80)))
    ref = synth.to_dataarray(z, "ref")
    sub = z[7:50, 11:70].copy()
    sub[3, 4] = np.nan
    t = Affine(synth.RES, 0, synth.X0 + 11 * synth.RES, 0, -synth.RES, synth.Y0 - 7 * synth.RES)
    p = synth.write_tif(tmp_path / "o.tif", np.nan_to_num(sub, nan=-9999), transform=t, nodata=-9999)
    pair = align_dsms(ref, open_dsm(p, chunks=16), chunks=16)
    assert not pair.resampled and pair.ref.shape == (43, 59) and pair.ref_window == (7, 50, 11, 70)
    o = pair.other.values
    assert np.isnan(o[3, 4]) and np.array_equal(np.nan_to_num(o, nan=0), np.nan_to_num(sub.astype(np.float32), nan=0))
    assert np.array_equal(pair.ref.values, z[7:50, 11:70].astype(np.float32))
    assert pair.ref.rio.transform() == t


def test_other_crs_and_resolution_are_resampled_blockwise_like_gdal(synth, tmp_path):
    z = synth.terrain(*synth.centres((90, 100)))
    ref = synth.to_dataarray(z, "ref")
    # other: UTM 33N-like? keep metric but another CRS (EPSG:3857) at 13 m
    src_t = Affine(synth.RES, 0, synth.X0, 0, -synth.RES, synth.Y0)
    dst_crs = "EPSG:3857"
    from rasterio.warp import calculate_default_transform

    dt, w, h = calculate_default_transform(synth.CRS, dst_crs, 100, 90, *ref.rio.bounds(), resolution=13.0)
    other = np.full((h, w), np.nan, np.float32)
    reproject(z.astype(np.float32), other, src_transform=src_t, src_crs=synth.CRS, dst_transform=dt, dst_crs=dst_crs,
              dst_nodata=np.nan, resampling=Resampling.cubic)
    p = tmp_path / "o.tif"
    with rasterio.open(p, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=dst_crs, transform=dt, nodata=np.nan) as ds:
        ds.write(other, 1)
    pair = align_dsms(ref, open_dsm(p, chunks=32), chunks=24)
    assert pair.resampled
    # oracle: GDAL warping the whole file at once onto the common grid
    whole = np.full(pair.ref.shape, np.nan, np.float32)
    reproject(other, whole, src_transform=dt, src_crs=dst_crs, src_nodata=np.nan, dst_transform=pair.transform,
              dst_crs=synth.CRS, dst_nodata=np.nan, resampling=Resampling.bilinear, tolerance=0.0)
    got = pair.other.values
    both = np.isfinite(got) & np.isfinite(whole)
    assert both.mean() > 0.9
    # GDAL warps a block from its own source window: values agree to < 1 cm (slopes ~ 0.3)
    assert np.nanmax(np.abs(got[both] - whole[both])) < 0.01
    assert np.median(np.abs(got[both] - whole[both])) < 5e-3
    # and it is the terrain (round trip through two resamplings, 13 m cells)
    inner = both.copy()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    assert np.median(np.abs(got - pair.ref.values)[inner]) < 0.5


def test_no_overlap_names_both_files(synth, tmp_path):
    z = synth.terrain(*synth.centres((20, 20)))
    a = synth.write_tif(tmp_path / "a.tif", z)
    b = synth.write_tif(tmp_path / "b.tif", z, transform=Affine(synth.RES, 0, synth.X0 + 1000, 0, -synth.RES, synth.Y0))
    with pytest.raises(NoOverlapError, match=r"a\.tif.*b\.tif"):
        align_dsms(open_dsm(a), open_dsm(b))


def test_open_dsm_errors(tmp_path):
    with pytest.raises(InputFileError, match="no such DSM file"):
        open_dsm(tmp_path / "missing.tif")
    p = tmp_path / "nocrs.tif"
    with rasterio.open(p, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32") as ds:
        ds.write(np.zeros((4, 4), np.float32), 1)
    with pytest.raises(InputFileError, match="no CRS"):
        open_dsm(p)



def test_zarr_product_round_trip_as_input(synth, tmp_path):
    from tiledsm.io import write_zarr

    z = synth.terrain(*synth.centres((40, 50)))
    p = write_zarr(synth.to_dataarray(z, "height"), tmp_path / "dsm.zarr")
    arr = open_dsm(p, chunks=16)
    assert arr.rio.crs.to_string() == synth.CRS and arr.rio.transform() == synth.to_dataarray(z).rio.transform()
    assert np.array_equal(arr.values, z.astype(np.float32))
