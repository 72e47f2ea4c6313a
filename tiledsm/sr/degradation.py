"""The image formation that SR inverts: the kernels that make a
low-resolution image from a high-resolution one.

The data generator (:func:`tiledsm.synth.degrade.degrade`) makes LR images
with them, and SRMD (:func:`tiledsm.sr.models.srmd.bicubic_kernel`) describes
its bicubic degradation with the same Keys kernel, so both live here, with
the networks that invert them, not in the generator.

A kernel is ``(scale, sigma) -> (weight(distance in input px), support
radius in input px)``; distances are between an output pixel's centre and
an input pixel's centre, in input pixels.
"""

from __future__ import annotations

import numpy as np

from tiledsm.errors import TiledsmError

__all__ = ["KERNELS", "keys_cubic", "gaussian_sigma"]


def keys_cubic(x, a: float = -0.5):
    """Keys' (1981) cubic convolution kernel at ``x`` (``a = -0.5``: the
    "bicubic" of MATLAB's ``imresize`` and of the SR literature); support
    ``|x| < 2``."""
    x = np.abs(x)
    return np.where(
        x <= 1, (a + 2) * x**3 - (a + 3) * x**2 + 1,
        np.where(x < 2, a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a, 0.0),
    )


def _bicubic_kernel(scale, sigma):
    return (lambda d: keys_cubic(d / scale)), 2.0 * scale


def gaussian_sigma(scale: float, sigma: float | None = None) -> float:
    """The Gaussian degradation's sigma, input pixels: ``sigma``, or half
    the scale factor when it is not given."""
    return 0.5 * scale if sigma is None else float(sigma)


def _gaussian_kernel(scale, sigma):
    s = gaussian_sigma(scale, sigma)
    if s <= 0:
        raise TiledsmError(f"degrade: gaussian sigma must be > 0, got {s}")
    return (lambda d: np.exp(-0.5 * (d / s) ** 2)), 4.0 * s


#: degradation kernels: name -> (scale, sigma) -> (kernel(distance in input px), support radius)
KERNELS = {"bicubic": _bicubic_kernel, "gaussian": _gaussian_kernel}
