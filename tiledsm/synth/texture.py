"""Ground texture (albedo) with a natural spectrum.

The ground albedo is ``mean + contrast * T(x, y)`` where ``T`` is a
unit-variance :class:`~tiledsm.synth.noise.SpectralField` whose 2-D power
spectrum falls as ``|f|**-beta`` (``beta = 2``: the ``1/f`` amplitude
spectrum of natural images). Its wavelengths run from ``max_wavelength``
down to ``nyquist_margin * 2 * gsd``, just below the Nyquist frequency of
the images, so rendering does not alias. Plane waves have incommensurate
random wavenumbers: the texture never repeats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiledsm.synth.noise import SpectralField, power_law_field

__all__ = ["TextureParams", "make_texture_field", "ground_albedo"]


@dataclass(frozen=True)
class TextureParams:
    """Texture parameters.

    Attributes
    ----------
    beta : float
        Spectral exponent of the 2-D power spectral density (2 = natural).
    mean, contrast : float
        Ground albedo mean and standard deviation (before clipping to
        [0.02, 1]).
    max_wavelength : float
        Longest wavelength, metres.
    nyquist_margin : float
        Shortest wavelength in units of the image Nyquist wavelength ``2 gsd``
        (> 1 keeps the texture band-limited below the image Nyquist).
    per_octave : int
        Plane waves per octave.
    """

    beta: float = 2.0
    mean: float = 0.35
    contrast: float = 0.12
    max_wavelength: float = 800.0
    nyquist_margin: float = 1.25
    per_octave: int = 40


def make_texture_field(rng: np.random.Generator, gsd: float, params: TextureParams) -> SpectralField:
    """Unit-variance texture field for images of ground sample distance ``gsd`` metres."""
    lmin = params.nyquist_margin * 2.0 * gsd
    return power_law_field(rng, (lmin, params.max_wavelength), params.beta, 1.0, params.per_octave)


def ground_albedo(tex: np.ndarray, params: TextureParams) -> np.ndarray:
    """Map the unit-variance texture to ground albedo in [0.02, 1] (float32)."""
    a = np.float32(params.mean) + np.float32(params.contrast) * tex
    return np.clip(a, 0.02, 1.0).astype(np.float32, copy=False)
