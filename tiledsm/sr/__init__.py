"""Single-image super-resolution before matching (bicubic, SRCNN, VDSR, SRMD).

Public API: :func:`build`, :func:`load_pretrained`, :func:`super_resolve`,
:func:`psnr`, :func:`ssim`; training in :mod:`tiledsm.sr.train`.
"""

from tiledsm.sr.infer import sr_array, super_resolve
from tiledsm.sr.metrics import psnr, ssim
from tiledsm.sr.registry import MODELS, SRError, build, load_pretrained, load_weights

__all__ = ["MODELS", "SRError", "build", "load_pretrained", "load_weights", "sr_array", "super_resolve", "psnr", "ssim"]
