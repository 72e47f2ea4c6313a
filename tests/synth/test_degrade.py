"""Degradation: PIL oracle for bicubic, exactness on ramps, geometry kept."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.rpc import RPC as RioRPC

from tiledsm.geometry import RPC
from tiledsm.synth import degrade
from tiledsm.synth.degrade import resample_matrix


def _write(path, img, rpc=None, dtype=None):
    dtype = dtype or img.dtype
    prof = dict(driver="GTiff", width=img.shape[1], height=img.shape[0], count=1, dtype=np.dtype(dtype).name)
    if rpc is not None:
        prof["rpcs"] = RioRPC.from_gdal(rpc.to_gdal())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", **prof) as ds:
            ds.write(img.astype(dtype), 1)


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(1), ds.rpcs


def test_bicubic_matches_pil_antialiased_bicubic():
    from PIL import Image

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1000, (64, 80))
    wy = resample_matrix(64, 2, "bicubic")
    wx = resample_matrix(80, 2, "bicubic")
    ours = wy @ img @ wx.T
    pil = np.asarray(Image.fromarray(img.astype(np.float32), mode="F").resize((40, 32), Image.Resampling.BICUBIC))
    np.testing.assert_allclose(ours[2:-2, 2:-2], pil[2:-2, 2:-2], atol=1e-2)


@pytest.mark.parametrize("method", ["bicubic", "gaussian"])
@pytest.mark.parametrize("scale", [2, 3, 4])
def test_ramps_are_reproduced_at_the_output_centres(method, scale):
    w = resample_matrix(100, scale, method)
    u = np.arange(100.0)
    out = w @ (3.0 * u + 7.0)
    centre = (np.arange(w.shape[0]) + 0.5) * scale - 0.5
    inner = slice(4, -4)
    np.testing.assert_allclose(out[inner], (3.0 * centre + 7.0)[inner], atol=1e-9)


@pytest.mark.parametrize("method", ["bicubic", "gaussian"])
def test_degrade_keeps_geometry(tmp_path, small_scene, method):
    """A bright spot placed at a ground point's projection lands where the
    scaled RPC projects that ground point."""
    rpc = small_scene.rpcs[0]
    lon, lat, h = rpc.lon_off + 0.1 * rpc.lon_scale, rpc.lat_off - 0.05 * rpc.lat_scale, rpc.height_off
    r, c = rpc.project(lon, lat, h)
    rows, cols = np.meshgrid(np.arange(192) + 0.5, np.arange(192) + 0.5, indexing="ij")
    img = 200 + 3000 * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 2.0**2))
    src = tmp_path / "hr.tif"
    _write(src, np.round(img), rpc, np.uint16)
    out = degrade(src, tmp_path / f"lr_{method}.tif", scale=2, method=method)
    low, rpcs = _read(out)
    assert low.shape == (96, 96) and low.dtype == np.uint16
    lr_rpc = RPC.from_gdal(rpcs.to_gdal())
    r2, c2 = lr_rpc.project(lon, lat, h)
    w = np.clip(low.astype(float) - 200, 0, None)
    rr, cc = np.meshgrid(np.arange(96) + 0.5, np.arange(96) + 0.5, indexing="ij")
    cr, ccol = (w * rr).sum() / w.sum(), (w * cc).sum() / w.sum()
    assert abs(cr - r2) < 0.05 and abs(ccol - c2) < 0.05
    assert abs(r2 - r / 2) < 1e-6 and abs(c2 - c / 2) < 1e-6


def test_degrade_noise_and_errors(tmp_path):
    from tiledsm.errors import InputFileError, TiledsmError

    img = np.full((64, 64), 1000.0)
    src = tmp_path / "flat.tif"
    _write(src, img, None, np.uint16)
    out, _ = _read(degrade(src, tmp_path / "n.tif", scale=2, method="gaussian", noise=4.0, seed=1))
    assert abs(out.mean() - 1000) < 1.0 and 3.5 < out.std() < 4.5
    with pytest.raises(InputFileError, match="missing.tif"):
        degrade(tmp_path / "missing.tif", tmp_path / "x.tif")
    with pytest.raises(TiledsmError, match="unknown method"):
        degrade(src, tmp_path / "x.tif", method="lanczos")
    assert not (tmp_path / "x.tif").exists()


def test_cli_parsers(tmp_path, small_scene):
    import argparse

    from tiledsm.cli import synth as cli

    parser = argparse.ArgumentParser(prog="tiledsm")
    cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["degrade", str(small_scene.views[1]), str(tmp_path / "lr.tif"), "--scale", "2"])
    assert args.func(args) == 0
    low, rpcs = _read(tmp_path / "lr.tif")
    assert low.shape == (96, 96) and rpcs is not None
    args = parser.parse_args(["synth", str(tmp_path / "s"), "--size", "64", "--views", "2", "--bh", "0.6",
                              "--chunk", "32", "--json"])
    assert args.func(args) == 0
    assert (tmp_path / "s" / "view_1.tif").exists() and (tmp_path / "s" / "truth_dsm.tif").exists()
