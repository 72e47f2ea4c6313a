"""Training writes loadable weights and a card; degradations are right."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tiledsm.sr import load_weights
from tiledsm.sr.models.srmd import SRMD, bicubic_kernel, gaussian_kernel
from tiledsm.sr.registry import SRError
from tiledsm.sr.train import TrainConfig, degrade_bicubic, degrade_blur_noise, synthetic_image, train


def test_train_writes_weights_and_card(tmp_path):
    cfg = TrainConfig(model="srmd", scale=2, out=str(tmp_path / "srmd_x2.pt"), steps=2, batch=2, patch=16,
                      use_skimage=False, synthetic=1, params={"layers": 3, "features": 8}, half=True, eval_crop=64)
    card = train(cfg, log=lambda m: None)
    assert card["steps"] == 2 and card["data"] == ["synthetic_image(seed=1000)"]
    assert set(card["heldout_psnr_db"]) == {"camera", "coffee"}
    model = load_weights(tmp_path / "srmd_x2.pt")
    assert model.card["steps"] == 2 and next(model.parameters()).dtype == torch.float32
    assert "| camera |" in (tmp_path / "srmd_x2.md").read_text()


def test_config_validation():
    with pytest.raises(SRError, match="multiple of scale"):
        TrainConfig(model="srcnn", scale=3, patch=32)
    with pytest.raises(SRError, match="nothing to train"):
        TrainConfig(model="bicubic")


def test_degradations():
    hr = torch.from_numpy(synthetic_image(0, 64))[None, None]
    lr = degrade_bicubic(hr, 2)
    assert lr.shape == (1, 1, 32, 32)
    # a constant image stays constant (antialiased kernel sums to 1)
    np.testing.assert_allclose(degrade_bicubic(torch.full((1, 1, 8, 8), 0.3), 2).numpy(), 0.3, atol=1e-6)
    # blur + direct downsampling without noise == scipy-free numpy oracle at one pixel
    out = degrade_blur_noise(hr, 2, torch.tensor([1.5]), torch.tensor([0.0]), centred=False)
    k = gaussian_kernel(1.5)
    i, j = 10, 12  # LR pixel -> HR centre (2i + 1, 2j + 1)
    patch = hr[0, 0, 2 * i + 1 - 7 : 2 * i + 1 + 8, 2 * j + 1 - 7 : 2 * j + 1 + 8].numpy()
    assert float(out[0, 0, i, j]) == pytest.approx(float((patch * k).sum()), abs=1e-5)
    noisy = degrade_blur_noise(hr, 2, torch.tensor([1.5]), torch.tensor([0.05]), torch.Generator().manual_seed(0), centred=False)
    assert float((noisy - out).std()) == pytest.approx(0.05, rel=0.1)


@pytest.mark.parametrize("scale", [2, 3, 4])
def test_centred_blur_noise_samples_lr_pixel_centres(scale):
    """Default sampling: LR pixel j sits at HR index coordinate (j + 0.5) s - 0.5
    (the corner convention of the RPCs). A symmetric blur keeps a ramp a ramp,
    so the LR value is the ramp at that point (analytic oracle)."""
    n = 16 * scale
    r, c = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64), indexing="ij")
    hr = torch.from_numpy(0.003 * r + 0.005 * c)[None, None]
    lr = degrade_blur_noise(hr, scale, torch.tensor([1.2]), torch.tensor([0.0]))[0, 0].numpy()
    j = np.arange(lr.shape[0])
    centre = (j + 0.5) * scale - 0.5
    expect = 0.003 * centre[:, None] + 0.005 * centre[None, :]
    inner = slice(4, -4)  # away from the reflected border
    np.testing.assert_allclose(lr[inner, inner], expect[inner, inner], atol=1e-6)


def _tiny(tmp_path, name, **kw):
    return TrainConfig(model="srcnn", scale=2, out=str(tmp_path / name), steps=24, batch=2, patch=16, use_skimage=False,
                       synthetic=1, params={"residual": True}, eval_crop=32, checkpoint_every=5, **kw)


def test_interrupted_training_continues_to_the_uninterrupted_weights(tmp_path):
    """Training is defined by its step count: a run stopped by the
    max_seconds safety stop says so on its card, keeps a checkpoint, and
    the same configuration continues from it to weights bit-identical to an
    uninterrupted run's (random states included)."""
    whole = train(_tiny(tmp_path, "whole.pt"), log=lambda m: None)
    assert whole["finished"] and whole["steps"] == 24
    assert not (tmp_path / "whole.pt.ckpt").exists()

    cfg = _tiny(tmp_path, "cut.pt")
    # stop after the first step (max_seconds ~ 0), then again part way, then finish
    first = train(TrainConfig(**{**cfg.__dict__, "max_seconds": 1e-9}), log=lambda m: None)
    assert not first["finished"] and first["steps"] == 1 and first["steps_planned"] == 24
    assert "NOT FINISHED" in (tmp_path / "cut.md").read_text()
    assert (tmp_path / "cut.pt.ckpt").exists()
    messages = []
    done = train(cfg, log=messages.append)
    assert any("resumed" in m and "step 1 of 24" in m for m in messages), messages
    assert done["finished"] and done["steps"] == 24 and not (tmp_path / "cut.pt.ckpt").exists()
    a = torch.load(tmp_path / "whole.pt", weights_only=False)["state_dict"]
    b = torch.load(tmp_path / "cut.pt", weights_only=False)["state_dict"]
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # another configuration never resumes that checkpoint
    train(TrainConfig(**{**cfg.__dict__, "max_seconds": 1e-9}), log=lambda m: None)
    with pytest.raises(SRError, match="checkpoint of another training configuration"):
        train(TrainConfig(**{**cfg.__dict__, "lr": 5e-4}), log=lambda m: None)


def test_training_never_overwrites_the_shipped_weights_by_accident():
    from pathlib import Path

    import tiledsm.sr

    shipped = Path(tiledsm.sr.__file__).resolve().parent / "weights" / "srcnn_x2.pt"
    with pytest.raises(SRError, match="--ship"):
        TrainConfig(model="srcnn", out=str(shipped))
    assert TrainConfig(model="srcnn", out=str(shipped), ship=True).ship


def test_card_lists_cache_images_with_checksums(tmp_path):
    import hashlib

    import cv2

    folder = tmp_path / "tiles"
    folder.mkdir()
    img = (synthetic_image(3, 64) * 255).astype(np.uint8)
    cv2.imwrite(str(folder / "t.png"), img)
    card = train(TrainConfig(model="srcnn", out=str(tmp_path / "m.pt"), steps=1, batch=1, patch=16, use_skimage=False,
                             synthetic=0, data_dirs=(str(folder),), eval_crop=32), log=lambda m: None)
    digest = hashlib.sha256((folder / "t.png").read_bytes()).hexdigest()[:16]
    assert card["data"] == [f"tiles/t.png sha256:{digest}"]


def test_bicubic_kernel_is_keys_kernel_stretched_by_the_scale():
    """Analytic oracle: Keys' cubic (a = -0.5) at t = |r| / 2 for scale 2 is
    1, 0.5625, 0, -0.0625, 0 at t = 0, 0.5, 1, 1.5, 2 (then zero)."""
    k = bicubic_kernel(2)
    w = np.array([-0.0625, 0, 0.5625, 1, 0.5625, 0, -0.0625])
    expect = np.zeros((15, 15))
    expect[4:11, 4:11] = np.outer(w, w) / w.sum() ** 2
    np.testing.assert_allclose(k, expect, atol=1e-12)
    assert bicubic_kernel(4).sum() == pytest.approx(1.0) and (bicubic_kernel(4) < 0).any()


def test_srmd_takes_the_bicubic_code_per_image_and_per_batch_item():
    torch.manual_seed(0)
    model = SRMD(scale=2, layers=3, features=8).eval()
    x = torch.rand(3, 1, 12, 12)
    code_bic = model.degradation_code("bicubic", 0.0)
    code_gauss = model.degradation_code(0.8, 0.0)
    # the bicubic kernel's negative lobes make a code no Gaussian has
    assert float((code_bic - code_gauss).abs().max()) > 0.01
    with torch.no_grad():
        mixed = model(x, blur_sigma=["bicubic", 0.8, "bicubic"], noise=[0.0, 0.01, 0.02])
        one = [model(x[i : i + 1], blur_sigma=b, noise=n) for i, (b, n) in enumerate((("bicubic", 0.0), (0.8, 0.01), ("bicubic", 0.02)))]
    torch.testing.assert_close(mixed, torch.cat(one))
    with pytest.raises(ValueError, match="bicubic"):
        model(x, blur_sigma="gaussian")


def test_train_with_a_share_of_bicubic_patches_scores_both_degradations(tmp_path):
    cfg = TrainConfig(model="srmd", scale=2, out=str(tmp_path / "srmd_x2.pt"), steps=2, batch=4, patch=16, bicubic_fraction=0.5,
                      use_skimage=False, synthetic=1, params={"layers": 3, "features": 8}, eval_crop=64)
    card = train(cfg, log=lambda m: None)
    assert set(card["heldout_psnr_bicubic_lr_db"]) == {"camera", "coffee"}
    # the bicubic-LR table scores bicubic on bicubic-made LR: the number evaluate() gives a Bicubic model
    from tiledsm.sr.models.bicubic import Bicubic
    from tiledsm.sr.train import evaluate, skimage_images

    held = {k: v[(v.shape[0] - 64) // 2:][:64, (v.shape[1] - 64) // 2:][:, :64] for k, v in skimage_images(("camera", "coffee")).items()}
    ref = evaluate(Bicubic(2), 2, held, degradation="bicubic")
    for name in ("camera", "coffee"):
        assert card["heldout_psnr_bicubic_lr_db"][name]["bicubic"] == pytest.approx(ref[name]["model"], abs=1e-9)
    assert "bicubic kernel" in (tmp_path / "srmd_x2.md").read_text()
    with pytest.raises(SRError, match="bicubic_fraction"):
        TrainConfig(model="srcnn", bicubic_fraction=0.5)


def test_gain_range_trains_on_darker_patches(tmp_path, monkeypatch):
    """With ``gain_range`` the network sees patches scaled down by a
    log-uniform gain: the HR targets of a step are darker than the images."""
    import tiledsm.sr.train as T

    seen = []
    real = T.F.mse_loss

    def spy(pred, hr):
        seen.append(float(hr.max()))
        return real(pred, hr)

    monkeypatch.setattr(T.F, "mse_loss", spy)
    base = dict(model="srcnn", scale=2, steps=3, batch=8, patch=16, use_skimage=False, synthetic=1, eval_crop=32)
    train(TrainConfig(out=str(tmp_path / "a.pt"), **base), log=lambda m: None)
    plain = list(seen)
    seen.clear()
    train(TrainConfig(out=str(tmp_path / "b.pt"), gain_range=(0.04, 0.2), **base), log=lambda m: None)
    assert min(plain) > 0.5 and max(seen) <= 0.2 * max(plain) + 1e-6
    with pytest.raises(SRError, match="gain_range"):
        TrainConfig(gain_range=(0.0, 1.0))
