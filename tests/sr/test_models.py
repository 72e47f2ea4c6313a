"""SR networks and registry: shapes, halos, bicubic vs OpenCV, duplicates."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tiledsm.sr import MODELS, SRError, build, load_pretrained
from tiledsm.sr.models import SRCNN, SRMD, VDSR
from tiledsm.sr.models._layers import PAD_MODES, PaddedConv2d, symmetric_pad
from tiledsm.sr.registry import Registry


def test_registry_refuses_duplicates():
    reg = Registry("test")
    reg.register("a", SRCNN)
    with pytest.raises(SRError, match="already registered"):
        reg.register("a", VDSR)
    with pytest.raises(SRError, match="already registered"):
        MODELS.register("srcnn", SRCNN)
    assert MODELS.names() == ["bicubic", "srcnn", "srcnn_residual", "vdsr", "srmd", "srmd_official"]
    assert build("srcnn_residual", scale=2).residual and not build("srcnn", scale=2).residual


def test_registry_unknown_and_bad_params():
    with pytest.raises(SRError, match="unknown model 'edsr'"):
        build("edsr", scale=2)
    with pytest.raises(SRError, match="bad parameters for 'vdsr'"):
        build("vdsr", scale=2, channels=3)


def test_missing_weights_say_no_weights(tmp_path):
    with pytest.raises(SRError, match="no weights for SR model 'srmd' at scale x2"):
        load_pretrained("srmd", 2, folder=tmp_path)
    assert load_pretrained("bicubic", 3, folder=tmp_path).scale == 3


def test_architectures_match_papers():
    convs = lambda m: [l for l in m.modules() if isinstance(l, PaddedConv2d)]  # noqa: E731
    c = convs(SRCNN(2))
    assert [l.kernel_size[0] for l in c] == [9, 1, 5] and [l.out_channels for l in c] == [64, 32, 1]
    v = convs(VDSR(2))
    assert len(v) == 20 and all(l.kernel_size == (3, 3) for l in v) and v[1].out_channels == 64
    s = convs(SRMD(3))
    assert len(s) == 12 and s[1].out_channels == 128 and s[0].in_channels == 1 + 15 + 1 and s[-1].out_channels == 9
    # every conv is preceded by explicit padding, symmetric as the method says: no implicit zero padding
    assert all(l.padding == (0, 0) and l.pad_mode == "symmetric" for l in c + v + s)
    assert all(l.pad_mode == "zeros" for l in convs(build("srmd_official", scale=2)))  # as its weights were trained


@pytest.mark.parametrize("pad", [1, 2, 4, 5])
def test_symmetric_pad_is_numpys(pad):
    x = torch.arange(2 * 5 * 7, dtype=torch.float32).reshape(1, 2, 5, 7)
    ref = np.pad(x.numpy(), ((0, 0), (0, 0), (pad, pad), (pad, pad)), mode="symmetric")
    np.testing.assert_array_equal(symmetric_pad(x, pad).numpy(), ref)
    with pytest.raises(ValueError, match="exceeds the image size"):
        symmetric_pad(x, 6)


@pytest.mark.parametrize("mode", PAD_MODES)
def test_padded_conv_equals_conv_of_padded_image(mode):
    torch.manual_seed(0)
    layer = PaddedConv2d(1, 3, 5, pad_mode=mode)
    x = torch.rand(1, 1, 9, 11)
    np_mode = {"symmetric": "symmetric", "reflect": "reflect", "zeros": "constant"}[mode]
    padded = torch.from_numpy(np.pad(x.numpy(), ((0, 0), (0, 0), (2, 2), (2, 2)), mode=np_mode))
    with torch.no_grad():
        ref = torch.nn.functional.conv2d(padded, layer.weight, layer.bias)
        np.testing.assert_allclose(layer(x).numpy(), ref.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="pad_mode must be one of"):
        PaddedConv2d(1, 1, 3, pad_mode="replicate")


@pytest.mark.parametrize("name,scale", [("bicubic", 2), ("srcnn", 3), ("vdsr", 2), ("srmd", 4), ("srmd_official", 4)])
def test_shapes(name, scale):
    m = build(name, scale=scale).eval()
    x = torch.rand(2, 1, 13, 17)
    kw = {"blur_sigma": 1.0, "noise": 0.01} if name == "srmd" else {}
    with torch.no_grad():
        assert m(x, **kw).shape == (2, 1, 13 * scale, 17 * scale)


def test_halos_from_receptive_field():
    # bicubic support 2 LR px + conv radius (HR px) / scale, rounded up
    assert build("bicubic", scale=2).halo == 2
    assert build("srcnn", scale=2).halo == 2 + 3  # (4 + 0 + 2) / 2
    assert build("srcnn", scale=4).halo == 2 + 2  # ceil(6 / 4)
    assert build("vdsr", scale=2).halo == 2 + 10  # 20 / 2
    assert build("vdsr", scale=3).halo == 2 + 7  # ceil(20 / 3)
    assert build("srmd", scale=2).halo == 12  # 12 layers on the LR grid
    assert build("srmd_official", scale=4).halo == 12  # the same on zero padding


@pytest.mark.parametrize("scale", [2, 3, 4])
def test_bicubic_matches_opencv(scale):
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (23, 31)).astype(np.float32)
    ref = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    with torch.no_grad():
        out = build("bicubic", scale=scale)(torch.from_numpy(img)[None, None])[0, 0].numpy()
    np.testing.assert_allclose(out, ref, atol=2e-5)


def test_untrained_vdsr_is_bicubic():
    x = torch.rand(1, 1, 20, 20)
    with torch.no_grad():
        np.testing.assert_array_equal(VDSR(2)(x).numpy(), build("bicubic", scale=2)(x).numpy())
