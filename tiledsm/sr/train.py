"""Training of the SR networks on images available offline.

Data (all read locally, nothing downloaded here):

- scikit-image's bundled images (``skimage.data``), as grey levels; the
  names in :data:`HELD_OUT` are never trained on and serve as the
  held-out test set;
- images in cache folders given by the user (``*.png``, ``*.jpg``,
  ``*.tif``; e.g. the NEON aerial tiles unzipped from the ``deepforest``
  wheel), as grey levels;
- synthetic renders (:func:`synthetic_image`: fractal relief shading plus
  roof-like rectangles).

Degradations (applied to random HR patches on the fly):

- ``"bicubic"`` (SRCNN, VDSR): antialiased bicubic downsampling by the
  scale (``torch.nn.functional.interpolate(mode="bicubic",
  antialias=True)``, MATLAB ``imresize``-like);
- ``"blur_noise"`` (SRMD): Gaussian blur (sigma uniform in
  ``blur_range`` HR px), direct downsampling (pixel ``[s//2::s]``), white
  Gaussian noise (std uniform in ``noise_range``, normalised units). With
  ``centred=True`` the blur kernel is shifted so that LR pixel ``j`` samples
  HR index coordinate ``(j + 0.5) s - 0.5``: the corner convention of
  :mod:`tiledsm.synth.degrade` and of the RPC that
  :func:`~tiledsm.sr.infer.super_resolve` attaches; this is the default.
  ``centred=False`` takes pixels ``s//2::s``, half an HR pixel off that
  convention for even scales: a network trained so shifts its output by
  half an HR pixel against its RPC.

All images are normalised to [0, 1] (8-bit sources divided by 255).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tiledsm.sr.metrics import psnr
from tiledsm.sr.models import Bicubic
from tiledsm.sr.models.srmd import BICUBIC, KERNEL_SIZE, gaussian_kernel
from tiledsm.sr.registry import SRError, build

__all__ = [
    "TrainConfig", "train", "load_images", "skimage_images", "synthetic_image",
    "degrade_bicubic", "degrade_blur_noise", "evaluate", "checkpoint_path", "HELD_OUT", "HELD_OUT_FILES", "TRAIN_SKIMAGE",
]

#: scikit-image images kept out of training (held-out test set)
HELD_OUT = ("camera", "coffee")
#: image files never trained on, whatever folder holds them: the NEON tile of
#: the held-out quality benchmark (``benchmarks/sr_quality.py``)
HELD_OUT_FILES = ("OSBS_029.png",)
#: scikit-image images used for training
TRAIN_SKIMAGE = (
    "astronaut", "brick", "chelsea", "coins", "grass", "gravel", "moon", "rocket",
    "hubble_deep_field", "immunohistochemistry", "text", "page", "retina",
)


@dataclass(frozen=True)
class TrainConfig:
    """Parameters of one training run (validated once, in ``__post_init__``).

    Attributes
    ----------
    model : str
        Registry name (``srcnn``, ``vdsr``, ``srmd``).
    scale : int
        Upscaling factor.
    out : str
        Weights file to write (``.pt``); the card goes beside it (``.md``).
    steps : int
        Optimiser steps: the schedule (learning-rate halvings at 60 % and
        85 %) and the result are defined by this count.
    max_seconds : float
        Safety stop only: when it is reached first, training stops with a
        checkpoint and the card says ``finished: false``; the same command
        continues from the checkpoint (the weights of an interrupted and
        continued run equal those of an uninterrupted one).
    batch : int
        Patches per step.
    patch : int
        HR patch side (pixels), a multiple of ``scale``.
    lr : float
        Adam learning rate (halved at 60 % and 85 % of the steps done).
    seed : int
        Seed of patch sampling and initialisation.
    data_dirs : tuple of str
        Image folders (e.g. ``../shared/data/sr_train``, the NEON aerial
        tiles); not committed, never downloaded. Files named in
        :data:`HELD_OUT_FILES` are skipped: they are the held-out test set.
    synthetic : int
        Number of synthetic renders (512 x 512) added to the data.
    use_skimage : bool
        Use scikit-image's bundled images (minus :data:`HELD_OUT`).
    degradation : str
        ``"bicubic"`` or ``"blur_noise"`` (default: ``blur_noise`` for
        SRMD, ``bicubic`` otherwise).
    blur_range, noise_range : tuple of float
        SRMD degradation families (HR px; normalised noise std).
    gain_range : tuple of float
        Each HR patch is multiplied by a gain drawn log-uniformly in this
        range (default ``(1, 1)``: none), so that a network meets the dark
        images of 12-16 bit sensors normalised by their bit depth (the s2p
        pair's values sit below 0.18 of 4095) as well as full-range ones.
    bicubic_fraction : float
        ``blur_noise`` only: share of the patches degraded by the
        antialiased bicubic kernel (then noise) instead of a Gaussian, with
        the bicubic kernel's code (``blur_sigma="bicubic"``), so that SRMD
        also serves LR images made the usual way.
    centred : bool
        ``blur_noise`` only: sample the LR pixels at their centres (corner
        convention, see the module notes) instead of at pixel ``s//2``.
    half : bool
        Store weights as float16 (keeps VDSR under 2 MB); cast back on load.
    params : dict
        Extra constructor parameters of the model.
    threads : int
        Torch threads.
    eval_crop : int or None
        Evaluate on the central ``eval_crop``-pixel square of each held-out
        image (default: the whole images).
    checkpoint : str or None
        Checkpoint file (default ``out`` + ``.ckpt``): written every
        ``checkpoint_every`` steps and at a safety stop, resumed when it
        belongs to the same configuration, removed when training finishes.
    checkpoint_every : int
        Steps between checkpoints.
    ship : bool
        Allow ``out`` inside the package's shipped weights folder
        (``tiledsm/sr/weights``); refused otherwise, so a training run never
        overwrites the shipped weights by accident.
    """

    model: str = "srcnn"
    scale: int = 2
    out: str = "weights.pt"
    steps: int = 2000
    max_seconds: float = 240.0
    batch: int = 16
    patch: int = 48
    lr: float = 1e-3
    seed: int = 0
    data_dirs: tuple[str, ...] = ()
    synthetic: int = 4
    use_skimage: bool = True
    degradation: str | None = None
    blur_range: tuple[float, float] = (0.2, 2.6)
    noise_range: tuple[float, float] = (0.0, 25.0 / 255.0)
    bicubic_fraction: float = 0.0
    gain_range: tuple[float, float] = (1.0, 1.0)
    centred: bool = True
    half: bool = False
    params: dict = field(default_factory=dict)
    threads: int = 1
    eval_crop: int | None = None
    checkpoint: str | None = None
    checkpoint_every: int = 200
    ship: bool = False

    def __post_init__(self) -> None:
        shipped = (Path(__file__).resolve().parent / "weights").resolve()
        if not self.ship and Path(self.out).resolve().parent == shipped:
            raise SRError(
                f"TrainConfig.out: {self.out} would overwrite the shipped weights in {shipped}; "
                "write elsewhere, or pass --ship (ship: true) to replace them on purpose"
            )
        if self.steps < 1 or self.checkpoint_every < 1:
            raise SRError(f"TrainConfig: steps and checkpoint_every must be >= 1, got {self.steps}, {self.checkpoint_every}")
        if self.degradation is None:
            object.__setattr__(self, "degradation", "blur_noise" if self.model == "srmd" else "bicubic")
        if self.degradation not in ("bicubic", "blur_noise"):
            raise SRError(f"TrainConfig.degradation: expected 'bicubic' or 'blur_noise', got {self.degradation!r}")
        if not 0.0 <= self.bicubic_fraction <= 1.0 or (self.bicubic_fraction and self.degradation != "blur_noise"):
            raise SRError(f"TrainConfig.bicubic_fraction: a share in [0, 1] of a blur_noise training, got {self.bicubic_fraction}")
        if self.patch % self.scale:
            raise SRError(f"TrainConfig.patch ({self.patch}) must be a multiple of scale ({self.scale})")
        if self.model == "bicubic":
            raise SRError("TrainConfig.model: bicubic has nothing to train")
        object.__setattr__(self, "data_dirs", tuple(str(c) for c in self.data_dirs))
        object.__setattr__(self, "blur_range", tuple(float(v) for v in self.blur_range))
        object.__setattr__(self, "noise_range", tuple(float(v) for v in self.noise_range))
        object.__setattr__(self, "gain_range", tuple(float(v) for v in self.gain_range))
        if not 0 < self.gain_range[0] <= self.gain_range[1]:
            raise SRError(f"TrainConfig.gain_range: expected 0 < low <= high, got {self.gain_range}")


# ----------------------------------------------------------------- data
def _grey(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    scale = 255.0 if img.dtype == np.uint8 else (65535.0 if img.dtype == np.uint16 else 1.0)
    img = img.astype(np.float32) / scale
    if img.ndim == 3:
        img = img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    return img


def skimage_images(names) -> dict[str, np.ndarray]:
    """Grey [0, 1] float32 versions of scikit-image's bundled images."""
    import skimage.data

    return {n: _grey(getattr(skimage.data, n)()) for n in names}


def synthetic_image(seed: int, size: int = 512) -> np.ndarray:
    """A synthetic "aerial" image in [0, 1]: hill-shaded fractal relief
    (1/f² spectrum) with flat-roofed rectangular blocks and a fine texture."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    k = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    k[0, 0] = 1.0
    spec = (rng.normal(size=(size, size)) + 1j * rng.normal(size=(size, size))) / k**1.6
    z = np.fft.ifft2(spec).real
    z = 40 * (z - z.min()) / np.ptp(z)
    for _ in range(40):
        h, w = rng.integers(8, 60, 2)
        r, c = rng.integers(0, size - 60, 2)
        z[r : r + h, c : c + w] = z[r : r + h, c : c + w].max() + rng.uniform(3, 15)
    gy, gx = np.gradient(z)
    shade = (1 - gx + gy) / np.sqrt(1 + gx**2 + gy**2)
    img = 0.5 + 0.25 * shade + 0.05 * rng.normal(size=(size, size)) * (rng.uniform(size=(size, size)) > 0.5)
    return np.clip(img, 0, 1).astype(np.float32)


def load_images(config: TrainConfig) -> tuple[list[np.ndarray], list[str]]:
    """Training images (grey, [0, 1]) and a description of where each came from."""
    import cv2

    images, sources = [], []
    if config.use_skimage:
        for n, img in skimage_images(TRAIN_SKIMAGE).items():
            images.append(img)
            sources.append(f"skimage.data.{n}")
    for d in config.data_dirs:
        folder = Path(d)
        if not folder.is_dir():
            raise SRError(f"TrainConfig.data_dirs: {folder} is not a folder")
        files = sorted(
            p for p in folder.iterdir()
            if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff") and p.name not in HELD_OUT_FILES
        )
        seen: set[str] = set()
        for p in sorted(files, key=lambda p: p.suffix.lower() in (".tif", ".tiff")):
            if p.stem in seen:  # same picture in two formats: keep the first (png/jpg)
                continue
            seen.add(p.stem)
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SRError(f"{p}: not a readable image")
            if img.ndim == 3:
                img = img[..., ::-1]  # BGR -> RGB
            images.append(_grey(img))
            sources.append(f"{folder.name}/{p.name} sha256:{file_sha256(p)[:16]}")
    for i in range(config.synthetic):
        images.append(synthetic_image(1000 + i))
        sources.append(f"synthetic_image(seed={1000 + i})")
    images = [im for im in images if min(im.shape) >= config.patch]
    if not images:
        raise SRError("training: no image large enough for the patch size")
    return images, sources


def file_sha256(path: Path) -> str:
    """Hex sha256 of a file's bytes (data and weight provenance on the cards)."""
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ---------------------------------------------------------- degradations
def degrade_bicubic(hr: torch.Tensor, scale: int) -> torch.Tensor:
    """Antialiased bicubic downsampling of ``(N, 1, H, W)`` by ``scale``."""
    return F.interpolate(hr, scale_factor=1 / scale, mode="bicubic", antialias=True, align_corners=False).clamp(0, 1)


def _sampling_kernel(sigma: float, scale: int, centred: bool) -> np.ndarray:
    """Blur kernel (``KERNEL_SIZE`` square, sum 1) applied before taking
    pixels ``s//2::s``; ``centred`` moves its centre by
    ``(s - 1) / 2 - s // 2`` HR px (-0.5 for even ``s``) so that the samples
    land on the LR pixel centres ``(j + 0.5) s - 0.5``."""
    shift = (scale - 1) / 2 - scale // 2 if centred else 0.0
    if shift == 0.0:
        return gaussian_kernel(sigma)
    r = np.arange(KERNEL_SIZE) - KERNEL_SIZE // 2 - shift
    if sigma <= 0:  # no blur: linear interpolation at the shifted centre
        g = np.maximum(0.0, 1.0 - np.abs(r))
    else:
        g = np.exp(-0.5 * (r / sigma) ** 2)
    k = np.outer(g, g)
    return k / k.sum()


def degrade_blur_noise(hr: torch.Tensor, scale: int, sigma: torch.Tensor, noise: torch.Tensor, gen: torch.Generator | None = None,
                       centred: bool = True) -> torch.Tensor:
    """SRMD degradation per batch item: Gaussian blur (``sigma[i]`` HR px,
    reflect border), direct downsampling (pixels ``s//2::s``; with
    ``centred``, at the LR pixel centres ``(j + 0.5) s - 0.5``), white noise
    of std ``noise[i]``."""
    kernels = torch.stack([torch.as_tensor(_sampling_kernel(float(s), scale, centred), dtype=hr.dtype) for s in sigma])[:, None]
    k = kernels.shape[-1]
    n = hr.shape[0]
    x = F.pad(hr, (k // 2,) * 4, mode="reflect")
    x = F.conv2d(x.transpose(0, 1), kernels, groups=n).transpose(0, 1)
    lr = x[..., scale // 2 :: scale, scale // 2 :: scale]
    return lr + noise.to(hr.dtype)[:, None, None, None] * torch.randn(lr.shape, generator=gen, dtype=hr.dtype)


def _sample_patches(images, n: int, size: int, rng: np.random.Generator) -> torch.Tensor:
    weights = np.array([im.size for im in images], float)
    idx = rng.choice(len(images), size=n, p=weights / weights.sum())
    out = np.empty((n, 1, size, size), np.float32)
    for b, i in enumerate(idx):
        im = images[i]
        r = rng.integers(0, im.shape[0] - size + 1)
        c = rng.integers(0, im.shape[1] - size + 1)
        p = im[r : r + size, c : c + size]
        p = np.rot90(p, rng.integers(4))
        if rng.integers(2):
            p = p[:, ::-1]
        out[b, 0] = p
    return torch.from_numpy(out)


# ------------------------------------------------------------ evaluation
def evaluate(model, scale: int, images: dict[str, np.ndarray] | None = None, degradation: str = "bicubic",
             blur_sigma: float = 1.0, noise: float = 0.0, centred: bool = True) -> dict[str, dict[str, float]]:
    """PSNR (8-bit peak, border = scale cropped) of ``model`` and of bicubic
    on held-out images degraded like the training data.

    Returns ``{image: {"model": dB, "bicubic": dB}}``.
    """
    from tiledsm.sr.infer import sr_array

    images = images if images is not None else skimage_images(HELD_OUT)
    bic = Bicubic(scale)
    out = {}
    gen = torch.Generator().manual_seed(0)
    for name, img in images.items():
        h, w = (np.array(img.shape) // scale) * scale
        hr = torch.from_numpy(np.ascontiguousarray(img[:h, :w]))[None, None]
        if degradation == "bicubic":
            lr = degrade_bicubic(hr, scale)
            kw = {"blur_sigma": BICUBIC, "noise": 0.0} if getattr(model, "takes_degradation", False) else {}
        else:
            lr = degrade_blur_noise(hr, scale, torch.tensor([blur_sigma]), torch.tensor([noise]), gen, centred=centred)
            kw = {"blur_sigma": blur_sigma, "noise": noise}
        lr_np = lr[0, 0].numpy()
        ref = hr[0, 0].numpy() * 255
        res = {}
        for label, m, extra in (("model", model, kw), ("bicubic", bic, {})):
            sr = sr_array(lr_np, m, value_scale=1.0, **extra) * 255
            res[label] = psnr(ref, np.clip(sr, 0, 255), data_range=255, border=scale)
        out[name] = res
    return out


# --------------------------------------------------------------- training
#: configuration fields that do not change the trained weights
_RUN_ONLY = ("out", "max_seconds", "threads", "checkpoint", "checkpoint_every", "ship", "eval_crop")


#: fields added after the first checkpoints were written, and their defaults
_ADDED_LATER = {"bicubic_fraction": 0.0, "gain_range": (1.0, 1.0)}


def _identity(config: TrainConfig) -> str:
    fields = {k: v for k, v in asdict(config).items() if k not in _RUN_ONLY}
    for name, default in _ADDED_LATER.items():  # checkpoints written before them stay valid
        if fields[name] == default:
            del fields[name]
    return json.dumps(fields, sort_keys=True, default=str)


def checkpoint_path(config: TrainConfig) -> Path:
    return Path(config.checkpoint or f"{config.out}.ckpt")


def _save_checkpoint(path: Path, config, model, opt, step, losses, seconds, rng, gen) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save({
        "identity": _identity(config), "step": step, "losses": losses, "seconds": seconds,
        "model": model.state_dict(), "opt": opt.state_dict(),
        "numpy_rng": rng.bit_generator.state, "torch_gen": gen.get_state(), "torch_rng": torch.get_rng_state(),
    }, tmp)
    tmp.replace(path)  # a killed save leaves the previous checkpoint intact


def train(config: TrainConfig, log=print) -> dict:
    """Train ``config.model`` for ``config.steps`` steps and write its
    weights file and card.

    A checkpoint of the same configuration (:func:`checkpoint_path`) is
    resumed: model, optimiser, step, losses and every random state, so
    the result does not depend on where an earlier run stopped.

    Returns the card (dict): data sources (with checksums), steps, whether
    the schedule finished, seconds, final loss, held-out PSNR of the model
    and of bicubic.
    """
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    images, sources = load_images(config)
    model = build(config.model, scale=config.scale, **config.params)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    s = config.scale
    losses: list[float] = []
    step, before = 0, 0.0
    ckpt = checkpoint_path(config)
    if ckpt.exists():
        state = torch.load(ckpt, weights_only=False)
        if state.get("identity") != _identity(config):
            raise SRError(f"{ckpt}: checkpoint of another training configuration; delete it or change --out")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        step, losses, before = int(state["step"]), list(state["losses"]), float(state["seconds"])
        rng.bit_generator.state = state["numpy_rng"]
        gen.set_state(state["torch_gen"])
        torch.set_rng_state(state["torch_rng"])
        log(f"resumed {ckpt} at step {step} of {config.steps}")
    t0 = time.perf_counter()
    milestones = (int(0.6 * config.steps), int(0.85 * config.steps))
    start = step
    # at least one step per call: a continued run always makes progress
    while step < config.steps and (step == start or time.perf_counter() - t0 < config.max_seconds):
        hr = _sample_patches(images, config.batch, config.patch, rng)
        if config.gain_range != (1.0, 1.0):
            lo, hi = np.log(config.gain_range)
            hr = hr * torch.exp(torch.rand(config.batch, generator=gen) * (hi - lo) + lo)[:, None, None, None]
        if config.degradation == "bicubic":
            lr_img = degrade_bicubic(hr, s)
            pred = model(lr_img)
        else:
            lo, hi = config.blur_range
            sigma = torch.rand(config.batch, generator=gen) * (hi - lo) + lo
            nlo, nhi = config.noise_range
            noise = torch.rand(config.batch, generator=gen) * (nhi - nlo) + nlo
            lr_img = degrade_blur_noise(hr, s, sigma, noise, gen, centred=config.centred)
            blur = sigma.tolist()
            if config.bicubic_fraction:
                bic = torch.rand(config.batch, generator=gen) < config.bicubic_fraction
                if bic.any():
                    lr_bic = degrade_bicubic(hr[bic], s)
                    lr_img[bic] = lr_bic + noise[bic][:, None, None, None] * torch.randn(lr_bic.shape, generator=gen)
                    blur = [BICUBIC if b else v for b, v in zip(bic.tolist(), blur)]
            pred = model(lr_img, blur_sigma=blur, noise=noise)
        loss = F.mse_loss(pred, hr)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        losses.append(loss.item())
        if step in milestones:
            for g in opt.param_groups:
                g["lr"] *= 0.5
        if step % 100 == 0:
            log(f"step {step} loss {np.mean(losses[-100:]):.3e} ({before + time.perf_counter() - t0:.0f} s)")
        if step % config.checkpoint_every == 0 and step < config.steps:
            _save_checkpoint(ckpt, config, model, opt, step, losses, before + time.perf_counter() - t0, rng, gen)
    finished = step >= config.steps
    if finished:
        ckpt.unlink(missing_ok=True)
    else:
        _save_checkpoint(ckpt, config, model, opt, step, losses, before + time.perf_counter() - t0, rng, gen)
        log(f"stopped by max_seconds at step {step} of {config.steps}: NOT finished; the same command continues from {ckpt}")
    seconds = before + time.perf_counter() - t0
    model.eval()
    eval_kw = {} if config.degradation == "bicubic" else {"blur_sigma": 1.0 * s / 2 + 0.2, "noise": 10 / 255}
    held_images = skimage_images(HELD_OUT)
    if config.eval_crop:
        c = config.eval_crop
        held_images = {k: v[(v.shape[0] - c) // 2 :][:c, (v.shape[1] - c) // 2 :][:, :c] for k, v in held_images.items()}
    held = evaluate(model, s, held_images, degradation=config.degradation, centred=config.centred, **eval_kw)
    card = {
        "model": config.model,
        "scale": s,
        "params": dict(config.params),
        "data": sources,
        "held_out": list(HELD_OUT) + list(HELD_OUT_FILES),
        "degradation": config.degradation,
        "steps": step,
        "steps_planned": config.steps,
        "finished": finished,
        "seconds": round(seconds, 1),
        "device": "cpu" if not next(model.parameters()).is_cuda else "cuda",
        "threads": config.threads,
        "final_loss_mse": float(np.mean(losses[-100:])) if losses else None,
        "heldout_psnr_db": held,
        **({"heldout_psnr_bicubic_lr_db": evaluate(model, s, held_images, degradation="bicubic")} if config.bicubic_fraction else {}),
        "heldout_eval": {"degradation": config.degradation, **eval_kw, "centred": config.centred, "peak": 255, "border": s, "crop": config.eval_crop},
        "config": {k: v for k, v in asdict(config).items() if k not in ("out", "checkpoint", "ship")},
        "torch": torch.__version__,
    }
    write_weights(model, config, card)
    return card


def _psnr_rows(scores: dict[str, dict[str, float]]) -> list[str]:
    return [f"| {name} | {r['model']:.2f} | {r['bicubic']:.2f} | {r['model'] - r['bicubic']:+.2f} |" for name, r in scores.items()]


def write_weights(model, config: TrainConfig, card: dict) -> Path:
    """Write ``{"name", "params", "state_dict", "card"}`` and a markdown card."""
    out = Path(config.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # the kernel basis stays float32: the degradation code is a projection on it, not a learned weight
    state = {k: (v.half() if config.half and v.is_floating_point() and not k.endswith("pca") else v).clone()
             for k, v in model.state_dict().items()}
    params = {"scale": config.scale, **config.params}
    torch.save({"name": config.model, "params": params, "state_dict": state, "card": json.dumps(card)}, out)
    lines = [
        f"# {config.model} x{config.scale} — tiledsm weights card",
        "",
        f"- file: `{out.name}` ({out.stat().st_size / 1e6:.2f} MB, {'float16' if config.half else 'float32'} storage, float32 at load)",
        ("" if card.get("finished", True) else f"- **NOT FINISHED**: stopped by max_seconds at step {card['steps']} of {card['steps_planned']}\n")
        + f"- trained: {card['steps']} Adam steps of {config.batch} patches {config.patch}x{config.patch} (HR), "
        f"{card['seconds']} s on {card['device']} with {card['threads']} thread(s), seed {config.seed}",
        f"- degradation: {config.degradation}" + (f" (blur sigma {config.blur_range} HR px, noise std {config.noise_range}, "
                                            f"{'centred' if config.centred else 'pixel s//2::s'} sampling"
                                            + (f"; {config.bicubic_fraction} of the patches by the bicubic kernel" if config.bicubic_fraction else "") + ")"
                                            if config.degradation == "blur_noise" else " (antialiased bicubic, torch)"),
        *([f"- brightness: each HR patch times a gain drawn log-uniformly in {config.gain_range}"] if config.gain_range != (1.0, 1.0) else []),
        f"- data ({len(card['data'])} images): " + ", ".join(card["data"]),
        f"- held out (never trained on): {', '.join(HELD_OUT)} (scikit-image), {', '.join(HELD_OUT_FILES)} (any data folder)",
        f"- final training MSE (normalised, last 100 steps): {card['final_loss_mse']:.3e}" if card["final_loss_mse"] is not None else "- final training MSE: none (no step)",
        "",
        "Held-out PSNR (dB, 8-bit peak, border of `scale` px cropped), measured after training:",
        "",
        "| image | model | bicubic | gain |",
        "|---|---|---|---|",
    ]
    lines += _psnr_rows(card["heldout_psnr_db"])
    if "heldout_psnr_bicubic_lr_db" in card:
        lines += ["", f"The same images degraded by the bicubic kernel alone (a share of {config.bicubic_fraction} of the "
                  "training patches), the model told `blur_sigma=\"bicubic\"`:", "",
                  "| image | model | bicubic | gain |", "|---|---|---|---|"]
        lines += _psnr_rows(card["heldout_psnr_bicubic_lr_db"])
    if card.get("note"):
        lines += ["", card["note"]]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    return out


def config_from_yaml(path: str | Path | None = None, **overrides) -> TrainConfig:
    """A :class:`TrainConfig` from a YAML mapping of its fields (top level or
    under ``train:``), with ``overrides`` applied. Relative ``data_dirs``
    in the file are relative to the file's folder, as in every recipe.
    Unknown fields raise :class:`~tiledsm.errors.RecipeError` naming the
    file and the field."""
    import dataclasses

    import yaml

    from tiledsm.errors import RecipeError

    values: dict = {}
    if path is not None:
        p = Path(path)
        if not p.exists():
            raise RecipeError(f"{p}: no such recipe")
        doc = yaml.safe_load(p.read_text()) or {}
        if not isinstance(doc, dict):
            raise RecipeError(f"{p}: expected a mapping at the top level")
        values = dict(doc.get("train", doc))
        values["data_dirs"] = [str(d) if Path(d).is_absolute() else str((p.parent / d).resolve()) for d in values.get("data_dirs") or ()]
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        for key in values:
            if key not in known:
                raise RecipeError(f"{p}: train.{key}: unknown field (known: {', '.join(sorted(known))})")
    values = {**values, **overrides}
    for key in ("data_dirs", "blur_range", "noise_range"):
        if key in values and values[key] is not None:
            values[key] = tuple(values[key])
    try:
        return TrainConfig(**values)
    except TypeError as exc:
        raise RecipeError(f"{path}: {exc}") from exc
