"""``tiledsm sr`` end to end on a real Pleiades crop, and the train-sr recipe."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import rasterio

from tiledsm.errors import RecipeError
from tiledsm.geometry import RPC
from tiledsm.cli import sr as sr_cli
from tiledsm.io import write_geotiff_with_rpc
from tiledsm.sr.train import config_from_yaml


def _parse(argv):
    p = argparse.ArgumentParser()
    sr_cli.add_parser(p.add_subparsers())
    return p.parse_args(argv)


def test_sr_command_writes_scaled_rpc_and_nodata(shared_data, tmp_path):
    src = shared_data("s2p_pair", "input_pair", "img_01.tif")
    with rasterio.open(src) as ds:
        img = ds.read(1, window=((300, 340), (400, 448))).astype(np.float32)
        rpc = RPC.from_gdal(ds.rpcs.to_dict()).cropped(300, 400)
    img[:5, :7] = np.nan
    lr = write_geotiff_with_rpc(img, tmp_path / "lr.tif", rpc, nodata=float("nan"))
    out = tmp_path / "hr"
    args = _parse(["sr", str(lr), str(out), "--model", "bicubic", "--scale", "2", "--chunk", "16",
                   "--scheduler", "synchronous", "--no-progress"])
    args.command = "sr"
    assert args.func(args) == 0
    with rasterio.open(out / "sr.tif") as ds:
        hr = ds.read(1)
        back = RPC.from_gdal(ds.rpcs.to_dict())
        assert ds.tags()["sr_model"] == "bicubic"
    assert hr.shape == (80, 96)
    assert back == RPC.from_gdal(rpc.scaled(2).to_gdal())
    assert np.isnan(hr[:10, :14]).all() and np.isfinite(hr[10:, 14:]).all()
    # away from nodata the values are OpenCV's bicubic
    import cv2

    ref = cv2.resize(img[5:, 7:], None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
    np.testing.assert_allclose(hr[20:-4, 24:-4], ref[10:-4, 10:-4], rtol=1e-5, atol=1e-2)


def test_train_recipe_parses_and_rejects_unknown(tmp_path):
    from pathlib import Path

    recipe = Path(__file__).resolve().parents[2] / "recipes" / "train_sr.yaml"
    cfg = config_from_yaml(recipe, model="vdsr", out=str(tmp_path / "v.pt"))
    assert cfg.model == "vdsr" and cfg.degradation == "bicubic" and cfg.patch % cfg.scale == 0
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  model: srcnn\n  epochs: 3\n")
    with pytest.raises(RecipeError, match="train.epochs: unknown field"):
        config_from_yaml(bad)


def _tiledsm(*argv):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "tiledsm", *map(str, argv)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def real_x4(tmp_path_factory):
    """A 256² crop of the real Pleiades image, degraded by 4 with `tiledsm degrade`."""
    from tests.conftest import require_shared

    root = tmp_path_factory.mktemp("x4")
    with rasterio.open(require_shared("s2p_pair", "input_pair", "img_01.tif")) as ds:
        img = ds.read(1, window=((300, 556), (400, 656)))
        rpc = RPC.from_gdal(ds.rpcs.to_dict()).cropped(300, 400)
    crop = write_geotiff_with_rpc(img, root / "crop.tif", rpc)
    r = _tiledsm("degrade", crop, root / "lr.tif", "--scale", "4")
    assert r.returncode == 0, r.stderr
    return root, img.astype(np.float64), rpc


def _psnr(truth, image, border=8):
    e = (image - truth)[border:-border, border:-border]
    return 10 * np.log10(truth.max() ** 2 / np.mean(e ** 2))


def test_sr_x4_by_x2_networks_twice_beats_bicubic_on_a_real_crop(real_x4):
    """srcnn/vdsr ship x2 weights only: `tiledsm sr --scale 4` applies them twice, says so (stderr, the
    output's sr_scheme tag), regenerates the RPC x4 and beats bicubic x4 against the original crop.
    Measured (crop rows 300-556, cols 400-656): bicubic 29.90 dB, srcnn 30.34, vdsr 30.51."""
    root, truth, rpc = real_x4
    psnr, tags = {}, {}
    for model in ("bicubic", "srcnn", "vdsr"):
        out = root / f"hr_{model}"
        r = _tiledsm("sr", root / "lr.tif", out, "--model", model, "--scale", "4", "--scheduler", "synchronous")
        assert r.returncode == 0, r.stderr
        with rasterio.open(out / "sr.tif") as ds:
            hr = ds.read(1).astype(np.float64)
            tags[model] = ds.tags()
            got = ds.rpcs.to_dict()
        with rasterio.open(root / "lr.tif") as ds:
            want = RPC.from_gdal(ds.rpcs.to_dict()).scaled(4).to_gdal()
        for key in ("LINE_OFF", "SAMP_OFF", "LINE_SCALE", "SAMP_SCALE"):
            assert float(got[key.lower()]) == pytest.approx(float(want[key]), abs=1e-6), key
        assert hr.shape == truth.shape
        psnr[model] = _psnr(truth, hr)
        if model != "bicubic":
            assert "x2 applied 2 times" in r.stderr and "x2 applied 2 times" in r.stdout
            assert tags[model]["sr_scheme"] == "x2 applied 2 times" and tags[model]["sr_scale"] == "4"
    assert "sr_scheme" not in tags["bicubic"]
    assert psnr["srcnn"] > psnr["bicubic"] + 0.35, psnr
    assert psnr["vdsr"] > psnr["bicubic"] + 0.5, psnr


def test_sr_x4_twice_is_tile_invariant(real_x4):
    """The two passes tiled (16-px tiles of the 64² LR image) equal the whole-image run; the RPC composes."""
    import xarray as xr

    from tiledsm.sr.infer import super_resolve

    root, _, _ = real_x4
    with rasterio.open(root / "lr.tif") as ds:
        lr = ds.read(1).astype(np.float32)
        rpc = RPC.from_gdal(ds.rpcs.to_dict())
    scene = xr.DataArray(lr, dims=("y", "x"), attrs={"rpc": rpc.to_gdal()})
    whole = super_resolve(scene, "srcnn", 4)
    tiled = super_resolve(scene, "srcnn", 4, chunks=16)
    assert whole.attrs["sr_scheme"] == "x2 applied 2 times" and whole.attrs["sr_scale"] == 4
    assert tiled.data.chunks[0][0] == 32  # the second pass re-tiled to 16 input px (x2), not 32
    np.testing.assert_allclose(tiled.values, whole.values, rtol=1e-5, atol=1e-2)
    assert RPC.from_gdal(whole.attrs["rpc"]).line_off == pytest.approx(rpc.scaled(4).line_off, abs=1e-9)


def test_sr_refuses_a_folder_of_another_run_without_overwrite(real_x4):
    """OUT holding a run of other options (its recipe.resolved.yaml) is refused, one line naming OUT and
    --overwrite, its product untouched; --overwrite replaces it; an output file name (the older form) is refused."""
    root, _, _ = real_x4
    out = root / "exists"
    r = _tiledsm("sr", root / "lr.tif", out, "--model", "bicubic", "--scale", "2", "--scheduler", "synchronous")
    assert r.returncode == 0, r.stderr
    before = (out / "sr.tif").read_bytes()
    r = _tiledsm("sr", root / "lr.tif", out, "--model", "bicubic", "--scale", "4")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("tiledsm sr: error:") and f"{out}: OUT:" in line and "--overwrite" in line, line
    assert (out / "sr.tif").read_bytes() == before
    r = _tiledsm("sr", root / "lr.tif", out, "--model", "bicubic", "--scale", "4", "--overwrite",
                 "--scheduler", "synchronous")
    assert r.returncode == 0, r.stderr
    with rasterio.open(out / "sr.tif") as ds:
        assert ds.shape == (256, 256)
    r = _tiledsm("sr", root / "lr.tif", root / "hr.tif", "--model", "bicubic")
    assert r.returncode == 2 and "OUT: is a run folder, not the output file" in r.stderr and not (root / "hr.tif").exists()
