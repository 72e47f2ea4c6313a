"""Seamless random fields evaluated at absolute coordinates.

Two building blocks make every synthetic scene deterministic by seed and
identical whatever the tiling:

- a counter-based hash (splitmix64) turning integer coordinates into uniform
  numbers, used for per-cell objects (buildings, trees) and per-pixel noise;
- :class:`SpectralField`, a sum of plane waves with a power-law spectrum
  ("spectral synthesis" without an FFT of the whole scene). On a separable
  grid it is one matrix product: ``cos(kx x + ky y + p)`` splits into
  ``cos(kx x) cos(ky y + p) - sin(kx x) sin(ky y + p)``, so a tile costs a
  BLAS GEMM of shape ``(ny, 2K) @ (2K, nx)``.

Coordinates are local metres (east, north) relative to the scene origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["SpectralField", "power_law_field", "hash_uniform", "cell_uniforms", "hash_normal"]

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(nogil=True, cache=True, inline="always")
def _mix(z):
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@numba.njit(nogil=True, cache=True)
def hash_uniform(seed, a, b, c):
    """Uniform number in [0, 1) from four integers (splitmix64 chain).

    Counter-based: the value depends only on ``(seed, a, b, c)``, never on
    evaluation order, so tiles computed independently agree exactly.
    """
    z = _mix(np.uint64(seed) * _GOLD + np.uint64(0x632BE59BD9B4E019))
    z = _mix(z ^ (np.uint64(np.int64(a)) * _GOLD))
    z = _mix(z ^ (np.uint64(np.int64(b)) * _M1))
    z = _mix(z ^ (np.uint64(np.int64(c)) * _M2))
    return (z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(nogil=True, cache=True)
def hash_normal(seed, a, b, c):
    """Standard normal number from four integers (Box-Muller on two hashes)."""
    u1 = hash_uniform(seed, a, b, 2 * c)
    u2 = hash_uniform(seed, a, b, 2 * c + 1)
    return math.sqrt(-2.0 * math.log(1.0 - u1)) * math.cos(2.0 * math.pi * u2)


@numba.njit(nogil=True, cache=True)
def _cell_uniforms(seed, stream, I, J, n, out):
    for p in range(I.size):
        for k in range(n):
            out[p, k] = hash_uniform(seed, I[p], J[p], stream * 4096 + k)


def cell_uniforms(seed: int, stream: int, I: np.ndarray, J: np.ndarray, n: int) -> np.ndarray:
    """``n`` uniform numbers per integer cell ``(I, J)`` (arrays, same shape).

    Returns an array of shape ``I.shape + (n,)``; ``stream`` separates
    independent uses (buildings, trees, ...) of the same cells.
    """
    I = np.asarray(I, np.int64)
    J = np.asarray(J, np.int64)
    out = np.empty((I.size, n), np.float64)
    _cell_uniforms(int(seed), int(stream), I.ravel(), J.ravel(), int(n), out)
    return out.reshape(I.shape + (n,))


@dataclass(frozen=True, eq=False)
class SpectralField:
    """A sum of plane waves ``sum_k amp_k cos(kx_k x + ky_k y + phase_k)``.

    Attributes
    ----------
    kx, ky : numpy.ndarray
        Angular wavenumbers, radians per metre (east, north).
    phase : numpy.ndarray
        Phases, radians.
    amp : numpy.ndarray
        Amplitudes, in the field's unit.
    """

    kx: np.ndarray
    ky: np.ndarray
    phase: np.ndarray
    amp: np.ndarray

    @property
    def rms(self) -> float:
        """Root mean square of the field (its spatial standard deviation)."""
        return float(np.sqrt(0.5 * np.sum(self.amp**2)))

    @property
    def bound(self) -> float:
        """Hard bound on ``|field|`` (sum of the amplitudes)."""
        return float(np.sum(np.abs(self.amp)))

    def variation_bound(self, distance: float) -> float:
        """Hard bound on ``|f(p) - f(q)|`` for ``|p - q| <= distance`` metres."""
        k = np.hypot(self.kx, self.ky)
        return float(np.sum(np.abs(self.amp) * np.minimum(2.0, k * distance)))

    def grid(self, x: np.ndarray, y: np.ndarray, dtype=np.float32) -> np.ndarray:
        """Evaluate on the separable grid ``x`` (columns) by ``y`` (rows).

        Parameters
        ----------
        x, y : numpy.ndarray
            1-D local coordinates, metres (east, north).

        Returns
        -------
        numpy.ndarray
            Shape ``(y.size, x.size)``; element ``[i, j]`` is the field at
            ``(x[j], y[i])``.
        """
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        ax = np.outer(self.kx, x)
        by = np.outer(self.ky, y) + self.phase[:, None]
        left = np.concatenate([np.cos(by), np.sin(by)]).T.astype(dtype)
        a = self.amp[:, None]
        right = np.concatenate([a * np.cos(ax), -a * np.sin(ax)]).astype(dtype)
        return left @ right

    def points(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Evaluate at scattered points (arrays of one shape), float64."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        out = np.zeros(np.broadcast(x, y).shape)
        for kx, ky, p, a in zip(self.kx, self.ky, self.phase, self.amp):
            out += a * np.cos(kx * x + ky * y + p)
        return out


def power_law_field(
    rng: np.random.Generator,
    wavelength_range: tuple[float, float],
    beta: float,
    rms: float,
    per_octave: int = 24,
) -> SpectralField:
    """An isotropic random field whose 2-D power spectrum falls as ``|f|**-beta``.

    Wavenumber magnitudes are stratified uniformly in ``log |k|`` (the same
    number of waves per octave, each jittered inside its stratum),
    directions are uniform and phases random. With that density the
    amplitude ``|k|**(1 - beta/2)`` gives a radially averaged power spectral
    density ``S(|f|) ~ |f|**-beta`` (natural images: ``beta ~ 2``; terrain:
    ``beta ~ 3-4``).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (fixes the field).
    wavelength_range : (float, float)
        Shortest and longest wavelengths, metres.
    beta : float
        Spectral exponent of the 2-D power spectral density.
    rms : float
        Standard deviation of the field.
    per_octave : int
        Number of plane waves per octave of wavelength.
    """
    lmin, lmax = sorted(float(v) for v in wavelength_range)
    octaves = max(math.log2(lmax / lmin), 1e-6)
    n = max(1, int(math.ceil(octaves * per_octave)))
    lo, hi = math.log(2 * math.pi / lmax), math.log(2 * math.pi / lmin)
    u = (np.arange(n) + rng.random(n)) / n
    k = np.exp(lo + u * (hi - lo))
    theta = rng.uniform(0.0, 2 * math.pi, n)
    phase = rng.uniform(0.0, 2 * math.pi, n)
    amp = k ** (1.0 - beta / 2.0)
    amp *= rms / np.sqrt(0.5 * np.sum(amp**2))
    return SpectralField(k * np.cos(theta), k * np.sin(theta), phase, amp)
