"""Name -> builder registry of SR models, and the shipped weights.

Models are registered by explicit imports below (no folder scanning). A
name can be registered once; a second registration raises
:class:`SRError`. Weights live in ``tiledsm/sr/weights/<name>_x<scale>.pt``
(a dict ``{"state_dict", "params", "card"}``) with a human-readable card
``<name>_x<scale>.md`` beside it.
"""

from __future__ import annotations

import functools

import json
from pathlib import Path
from typing import Callable

import torch

from tiledsm.errors import TiledsmError
from tiledsm.sr.models import SRCNN, SRMD, VDSR, Bicubic, OfficialSRMD, SRModel

__all__ = ["SRError", "Registry", "MODELS", "build", "load_pretrained", "load_weights", "available_weights", "weight_chain",
           "chain_scheme", "WEIGHTS_DIR"]

#: folder of the shipped state_dicts and their cards
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


class SRError(TiledsmError):
    """Raised for an unknown SR model name, a duplicate registration, missing
    or mismatching weights, or an invalid SR request."""


class Registry:
    """A dict of ``name -> builder`` that refuses duplicate names."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._builders: dict[str, Callable[..., SRModel]] = {}

    def register(self, name: str, builder: Callable[..., SRModel]) -> Callable[..., SRModel]:
        """Add ``builder`` under ``name``; raise :class:`SRError` if taken."""
        if name in self._builders:
            raise SRError(f"{self.kind} registry: name {name!r} is already registered ({self._builders[name]!r})")
        self._builders[name] = builder
        return builder

    def __contains__(self, name: object) -> bool:
        return name in self._builders

    def names(self) -> list[str]:
        """Registered names, in registration order."""
        return list(self._builders)

    def build(self, name: str, **params) -> SRModel:
        """Build model ``name`` with ``params`` (passed to its constructor)."""
        if name not in self._builders:
            raise SRError(f"{self.kind} registry: unknown model {name!r}; known: {', '.join(self._builders)}")
        try:
            return self._builders[name](**params)
        except TypeError as exc:
            raise SRError(f"{self.kind} registry: bad parameters for {name!r}: {exc}") from exc


#: the SR model registry
MODELS = Registry("SR model")
MODELS.register("bicubic", Bicubic)
MODELS.register("srcnn", SRCNN)
#: variant (not in the paper): SRCNN plus a global bicubic skip. Kept because
#: it measurably wins at the same CPU schedule (+0.17 / +0.20 dB held out on
#: camera / coffee, 3000 steps: see its card and the README)
MODELS.register("srcnn_residual", functools.partial(SRCNN, residual=True))
MODELS.register("vdsr", VDSR)
MODELS.register("srmd", SRMD)
#: the authors' published weights, converted (tiledsm.sr.ncnn)
MODELS.register("srmd_official", OfficialSRMD)

#: models that need no weights
WEIGHTLESS = frozenset({"bicubic"})


def build(name: str, **params) -> SRModel:
    """Build a (randomly initialised) model from :data:`MODELS`."""
    return MODELS.build(name, **params)


def weights_path(name: str, scale: int, folder: Path = WEIGHTS_DIR) -> Path:
    """Path of the weights file of ``name`` at ``scale``."""
    return Path(folder) / f"{name}_x{int(scale)}.pt"


def weight_chain(name: str, scale: int, folder: Path = WEIGHTS_DIR) -> tuple[int, ...] | None:
    """The shipped scales that make ``scale`` for model ``name``:
    ``(scale,)`` when it has weights for ``scale`` (or needs none), else
    ``(2, 2, ...)`` when ``scale`` is a power of two and the x2 weights
    exist (the network applied repeatedly, a stated substitute for
    missing native weights), else ``None``."""
    scale = int(scale)
    if name in WEIGHTLESS or weights_path(name, scale, folder).exists():
        return (scale,)
    n = scale.bit_length() - 1
    if scale > 2 and scale == 1 << n and weights_path(name, 2, folder).exists():
        return (2,) * n
    return None


def chain_scheme(chain: tuple[int, ...]) -> str | None:
    """How a :func:`weight_chain` reaches its scale, for attrs and logs:
    ``"x2 applied 2 times"``, or ``None`` for native weights (one pass)."""
    return None if len(chain) == 1 else f"x{chain[0]} applied {len(chain)} times"


def available_weights(folder: Path = WEIGHTS_DIR) -> list[tuple[str, int]]:
    """``(name, scale)`` pairs with a weights file in ``folder``."""
    out = []
    for p in sorted(Path(folder).glob("*_x*.pt")):
        name, _, s = p.stem.rpartition("_x")
        if s.isdigit():
            out.append((name, int(s)))
    return out


def load_weights(path: str | Path, device: str = "cpu") -> SRModel:
    """Build a model from a weights file written by :func:`tiledsm.sr.train.train`.

    The file holds ``{"name", "params", "state_dict", "card"}``; half-precision
    tensors are cast back to float32. The card is attached as ``model.card``.
    """
    path = Path(path)
    if not path.exists():
        raise SRError(f"{path}: no such weights file")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        name, params, state = blob["name"], dict(blob["params"]), blob["state_dict"]
    except Exception as exc:  # corrupt file, wrong layout
        raise SRError(f"{path}: not a tiledsm SR weights file ({exc})") from exc
    model = build(name, **params)
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in state.items()}
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise SRError(f"{path}: weights do not fit {name}({params}): {exc}") from exc
    model.card = json.loads(blob.get("card", "{}")) if isinstance(blob.get("card"), str) else blob.get("card", {})
    model.weights_file = str(path)
    return model.to(device).eval()


def load_pretrained(name: str, scale: int, device: str = "cpu", folder: Path = WEIGHTS_DIR) -> SRModel:
    """The shipped model ``name`` for ``scale``, in eval mode.

    ``bicubic`` needs no weights. For a CNN without a shipped weights file
    this raises :class:`SRError` saying "no weights" and listing what is
    shipped (train some with ``tiledsm train-sr`` and pass the file).
    """
    if name not in MODELS:
        raise SRError(f"SR model registry: unknown model {name!r}; known: {', '.join(MODELS.names())}")
    if name in WEIGHTLESS:
        return build(name, scale=scale).to(device).eval()
    path = weights_path(name, scale, folder)
    if not path.exists():
        have = ", ".join(f"{n} x{s}" for n, s in available_weights(folder)) or "none"
        raise SRError(
            f"no weights for SR model {name!r} at scale x{scale}: {path} does not exist "
            f"(shipped weights: {have}); train them with `tiledsm train-sr` and pass the file "
            f"(--weights), or use a model that has weights"
        )
    model = load_weights(path, device)
    if model.scale != scale:
        raise SRError(f"{path}: weights are for scale x{model.scale}, asked for x{scale}")
    return model
