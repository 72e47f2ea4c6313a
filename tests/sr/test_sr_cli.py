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
    out = tmp_path / "hr.tif"
    args = _parse(["sr", str(lr), str(out), "--model", "bicubic", "--scale", "2", "--chunk", "16",
                   "--scheduler", "synchronous", "--no-progress"])
    assert args.func(args) == 0
    with rasterio.open(out) as ds:
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
