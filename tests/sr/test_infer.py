"""Tiled SR == whole-image SR, nodata, attrs (RPC regenerated)."""

from __future__ import annotations

import dask
import numpy as np
import pytest
import torch
import xarray as xr

from tiledsm.sr import SRError, build, sr_array, super_resolve
from tiledsm.sr.infer import _merge_small_chunks, value_scale_for

VALUE_SCALE = 4095.0  # 12-bit sensor


def _random_model(name: str, scale: int = 2):
    """A model with every parameter random (no zero-initialised layer)."""
    torch.manual_seed(0)
    m = build(name, scale=scale)
    with torch.no_grad():
        for p in m.parameters():
            fan_in = p[0].numel() if p.ndim > 1 else 1
            p.normal_(0.0, 1.2 / np.sqrt(fan_in))
        for b in m.buffers():
            if b.dtype.is_floating_point and b.ndim == 1:  # batch-norm statistics
                b.uniform_(0.5, 1.5)
    return m.eval()


def _image(shape=(96, 80), seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, VALUE_SCALE, shape).astype(np.float32)


def _compute(arr):
    with dask.config.set(scheduler="synchronous"):
        return arr.compute()


DEG = {"srmd": {"blur_sigma": 1.3, "noise": 20.0}}


@pytest.mark.parametrize("name", ["bicubic", "srcnn", "vdsr", "srmd", "srmd_official"])
def test_tiled_equals_whole(name):
    model = _random_model(name)
    img = _image()
    kw = DEG.get(name, {})
    whole = sr_array(img, model, value_scale=VALUE_SCALE, **kw)
    assert whole.shape == (192, 160)
    assert np.std(whole) > 0.01 * VALUE_SCALE  # the random network does something
    for chunk in (32, 48, 64):
        scene = xr.DataArray(img, dims=("y", "x")).chunk({"y": chunk, "x": chunk})
        out = super_resolve(scene, model, 2, value_scale=VALUE_SCALE, **kw)
        assert out.data.chunks[0][0] == 2 * min(chunk, 96) and out.data.numblocks[0] > 1
        tiled = _compute(out).values
        assert np.max(np.abs(tiled - whole)) / VALUE_SCALE <= 1e-5, (name, chunk)


def test_halo_is_needed():
    """One pixel less of halo gives a different result: the halo is tight."""
    model = _random_model("srcnn")
    img = _image()
    whole = sr_array(img, model, value_scale=VALUE_SCALE)

    class Short(type(model)):
        halo = property(lambda self: super().halo - 1)

    short = Short(2)
    short.load_state_dict(model.state_dict())
    out = super_resolve(xr.DataArray(img, dims=("y", "x")).chunk(32), short.eval(), 2, value_scale=VALUE_SCALE)
    assert np.max(np.abs(_compute(out).values - whole)) / VALUE_SCALE > 1e-3


def test_band_axis_and_nan_nodata():
    model = _random_model("srcnn", 3)
    img = np.stack([_image(seed=1)[:40, :50], _image(seed=2)[:40, :50]])
    img[0, 10:14, 20:30] = np.nan
    img[1, :, :3] = np.nan
    scene = xr.DataArray(img, dims=("band", "y", "x"), coords={"band": [1, 2]}).chunk({"band": 1, "y": 16, "x": 24})
    out = _compute(super_resolve(scene, model, 3, value_scale=VALUE_SCALE))
    assert out.shape == (2, 120, 150) and out.dtype == np.float32
    for b in range(2):
        whole = sr_array(img[b], model, value_scale=VALUE_SCALE)
        expected_nan = np.kron(np.isnan(img[b]), np.ones((3, 3), bool))
        np.testing.assert_array_equal(np.isnan(out.values[b]), expected_nan)
        np.testing.assert_allclose(out.values[b], whole, atol=1e-5 * VALUE_SCALE, equal_nan=True)
    np.testing.assert_array_equal(out.band.values, [1, 2])


def test_attrs_coords_and_value_scale():
    img = _image((20, 30))
    scene = xr.DataArray(img, dims=("y", "x"), coords={"y": np.arange(20) + 0.5, "x": np.arange(30) + 0.5},
                         attrs={"bit_depth": 12, "camera_source": "x"})
    out = super_resolve(scene, "bicubic", 2)
    assert out.attrs["sr_value_scale"] == 4095.0 and out.attrs["sr_model"] == "bicubic" and out.attrs["sr_scale"] == 2
    assert out.attrs["camera_source"] == "x"
    # corner convention: HR pixel centres at (k + 0.5) / 2 in LR pixel units
    np.testing.assert_allclose(out.x.values, (np.arange(60) + 0.5) / 2)
    assert value_scale_for(xr.DataArray(np.array([[0, 3000.0]]))) == 4095.0
    assert value_scale_for(xr.DataArray(np.array([[0, 200]], np.uint8))) == 255.0
    assert value_scale_for(xr.DataArray(np.array([[0, 1500.0]]))) == 2047.0


def test_degradation_arguments_checked():
    scene = xr.DataArray(_image((20, 20)), dims=("y", "x"))
    with pytest.raises(SRError, match="takes no degradation"):
        super_resolve(scene, build("srcnn", scale=2), 2, blur_sigma=1.0, value_scale=VALUE_SCALE)
    with pytest.raises(SRError, match="needs blur_sigma"):
        super_resolve(scene, build("srmd", scale=2), 2, value_scale=VALUE_SCALE)
    with pytest.raises(SRError, match="'bicubic'"):
        super_resolve(scene, build("srmd", scale=2), 2, blur_sigma="box", value_scale=VALUE_SCALE)
    out = super_resolve(scene, build("srmd", scale=2), 2, blur_sigma="bicubic", noise=0.0, value_scale=VALUE_SCALE)
    assert out.attrs["sr_blur_sigma"] == "bicubic" and out.shape == (40, 40)
    with pytest.raises(SRError, match="built for scale x2, asked for x3"):
        super_resolve(scene, build("srcnn", scale=2), 3)


def test_merge_small_chunks():
    assert _merge_small_chunks((64, 64, 5), 12) == (64, 69)
    assert _merge_small_chunks((5, 64), 12) == (69,)
    assert _merge_small_chunks((8,), 12) == (8,)


def test_georeferenced_scene_keeps_crs_with_finer_transform():
    import rioxarray  # noqa: F401
    from affine import Affine

    x = 300000.25 + 0.5 * np.arange(30)
    y = 7650000.0 - 0.5 * np.arange(20)
    scene = xr.DataArray(_image((20, 30)), dims=("y", "x"), coords={"y": y, "x": x}).rio.write_crs("EPSG:32740")
    out = super_resolve(scene, "bicubic", 2, value_scale=VALUE_SCALE)
    assert out.rio.crs.to_epsg() == 32740
    assert out.rio.transform() == scene.rio.transform() @ Affine.scale(0.5)
    assert out.rio.transform(recalc=True).almost_equals(out.rio.transform())
