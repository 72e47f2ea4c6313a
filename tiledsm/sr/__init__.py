"""Single-image super-resolution before matching (bicubic, SRCNN, VDSR, SRMD).

Public API: :func:`build`, :func:`load_pretrained`, :func:`super_resolve`,
:func:`psnr`, :func:`ssim`; training in :mod:`tiledsm.sr.train`; the
``pipeline: sr`` stage (``tiledsm sr``) in :mod:`tiledsm.sr.recipe`,
:mod:`tiledsm.sr.plan` and :mod:`tiledsm.sr.run`.

The names are imported on first use (PEP 562): importing the stage's recipe
(every command does, through :data:`tiledsm.pipelines.PIPELINES`) does not
import torch.
"""

from __future__ import annotations

import importlib

#: public name -> the module that defines it
_HOMES = {
    "sr_array": "tiledsm.sr.infer", "super_resolve": "tiledsm.sr.infer",
    "psnr": "tiledsm.sr.metrics", "ssim": "tiledsm.sr.metrics",
    "MODELS": "tiledsm.sr.registry", "SRError": "tiledsm.sr.registry", "build": "tiledsm.sr.registry",
    "load_pretrained": "tiledsm.sr.registry", "load_weights": "tiledsm.sr.registry",
}

__all__ = ["MODELS", "SRError", "build", "load_pretrained", "load_weights", "sr_array", "super_resolve", "psnr", "ssim"]


def __getattr__(name: str):
    if name in _HOMES:
        return getattr(importlib.import_module(_HOMES[name]), name)
    raise AttributeError(f"module 'tiledsm.sr' has no attribute {name!r}")
