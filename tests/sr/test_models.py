"""SR networks and registry: shapes, halos, bicubic vs OpenCV, duplicates."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tiledsm.sr import MODELS, SRError, build, load_pretrained
from tiledsm.sr.models import SRCNN, SRMD, VDSR
from tiledsm.sr.models._layers import ReflectConv2d
from tiledsm.sr.registry import Registry


def test_registry_refuses_duplicates():
    reg = Registry("test")
    reg.register("a", SRCNN)
    with pytest.raises(SRError, match="already registered"):
        reg.register("a", VDSR)
    with pytest.raises(SRError, match="already registered"):
        MODELS.register("srcnn", SRCNN)
    assert MODELS.names() == ["bicubic", "srcnn", "vdsr", "srmd", "srmd_official"]


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
    convs = lambda m: [l for l in m.modules() if isinstance(l, ReflectConv2d)]  # noqa: E731
    c = convs(SRCNN(2))
    assert [l.kernel_size[0] for l in c] == [9, 1, 5] and [l.out_channels for l in c] == [64, 32, 1]
    v = convs(VDSR(2))
    assert len(v) == 20 and all(l.kernel_size == (3, 3) for l in v) and v[1].out_channels == 64
    s = convs(SRMD(3))
    assert len(s) == 12 and s[1].out_channels == 128 and s[0].in_channels == 1 + 15 + 1 and s[-1].out_channels == 9
    # every conv is preceded by reflect padding: no implicit zero padding
    assert all(l.padding == (0, 0) for l in c + v + s)


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
