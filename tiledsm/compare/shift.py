"""Subpixel translation of a height grid with a separable kernel (Keys
cubic convolution or linear), whole or at chosen cells: the shift applied
by the co-registration (:mod:`tiledsm.compare.coreg`).

Convention: ``out[i, j] = a(i - dy, j - dx)``: the content moves ``+dy``
rows and ``+dx`` columns; cells whose interpolation support touches a NaN
or leaves the array are NaN.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tiledsm.errors import TiledsmError

__all__ = ["ShiftKernelError", "kernel_taps", "shift_halo", "shift_array", "shifted_at"]


class ShiftKernelError(TiledsmError):
    """Raised for an unknown shift kernel name."""


def kernel_taps(d: float, kernel: str) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``o`` and weights ``w`` with ``out[i] = sum_k w_k in[i + o_k]`` = ``in(i - d)``."""
    n = math.floor(d)
    f = d - n
    if abs(f) < 1e-12:
        return np.array([-n]), np.array([1.0])
    # sample position p = i - d = i - n - 1 + u with u = 1 - f in (0, 1)
    u = 1.0 - f
    base = -n - 1
    if kernel == "linear":
        return np.array([base, base + 1]), np.array([1.0 - u, u])
    if kernel == "cubic":  # Keys (1981) cubic convolution, a = -0.5
        a = -0.5

        def w(t):
            t = abs(t)
            if t <= 1:
                return (a + 2) * t**3 - (a + 3) * t**2 + 1
            if t < 2:
                return a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a
            return 0.0

        return np.array([base - 1, base, base + 1, base + 2]), np.array([w(u + 1), w(u), w(1 - u), w(2 - u)])
    raise ShiftKernelError(f"unknown shift kernel {kernel!r}: one of 'linear', 'cubic'")


def shift_halo(dy: float, dx: float, kernel: str = "cubic") -> int:
    """Halo (pixels) a block needs to be shifted by ``(dy, dx)`` on its own."""
    oy, _ = kernel_taps(dy, kernel)
    ox, _ = kernel_taps(dx, kernel)
    return int(max(np.abs(oy).max(), np.abs(ox).max()))


def shift_array(a: np.ndarray, dy: float, dx: float, kernel: str = "cubic") -> np.ndarray:
    """Translate an image by a constant subpixel offset.

    ``out[i, j] = a(i - dy, j - dx)`` (content moves ``+dy`` rows, ``+dx``
    columns), interpolated separably with the given kernel ("cubic": Keys
    cubic convolution a = -0.5; "linear"). Output cells whose support
    touches a NaN or leaves the array are NaN. Integer shifts are exact.
    Because the weights are the same for every cell, a block shifted with a
    halo of :func:`shift_halo` pixels equals the same cells of the whole
    array shifted (bit for bit).
    """
    out = np.ascontiguousarray(a, dtype=np.float64)
    for axis, d in ((0, dy), (1, dx)):
        offs, wts = kernel_taps(d, kernel)
        keep = wts != 0.0
        res = np.empty(out.shape, dtype=np.float64)
        _shift_axis(out, offs[keep].astype(np.int64), wts[keep].astype(np.float64), axis, res)
        out = res
    return out.astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _shift_axis(a, offs, wts, axis, out):  # pragma: no cover - compiled
    """``out[i, j] = sum_k wts[k] * a[(i, j) + offs[k] along axis]``, NaN outside ``a``.

    The taps are added in order (``acc = w0 a0; acc = acc + w1 a1; ...``), the
    operations of the array expression ``sum(w * shifted)``, so the result is
    bit for bit the same as numpy's.
    """
    H, W = a.shape
    for i in range(H):
        for k in range(offs.size):
            w = wts[k]
            if axis == 0:
                r = i + offs[k]
                inside = 0 <= r < H
                for j in range(W):
                    term = w * (a[r, j] if inside else np.nan)
                    out[i, j] = term if k == 0 else out[i, j] + term
            else:
                for j in range(W):
                    c = j + offs[k]
                    term = w * (a[i, c] if 0 <= c < W else np.nan)
                    out[i, j] = term if k == 0 else out[i, j] + term


def shifted_at(a: np.ndarray, index: np.ndarray, dy: float, dx: float, kernel: str = "cubic") -> np.ndarray:
    """``shift_array(a, dy, dx, kernel).ravel()[index]`` computed at those
    cells only (float32): the same taps, weights and order of additions,
    so bit for bit the same values, at the cost of ``len(index)`` cells."""
    oy, wy = kernel_taps(dy, kernel)
    ox, wx = kernel_taps(dx, kernel)
    ky, kx = wy != 0.0, wx != 0.0
    out = np.empty(index.size, dtype=np.float64)
    _shift_at(np.ascontiguousarray(a, dtype=np.float32), np.asarray(index, np.int64), oy[ky].astype(np.int64),
              wy[ky].astype(np.float64), ox[kx].astype(np.int64), wx[kx].astype(np.float64), out)
    return out.astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _shift_at(a, index, oy, wy, ox, wx, out):  # pragma: no cover - compiled
    """:func:`_shift_axis` along rows then columns, evaluated at the flat ``index`` cells."""
    H, W = a.shape
    for n in range(index.size):
        i = index[n] // W
        j = index[n] % W
        acc = 0.0
        for m in range(ox.size):
            c = j + ox[m]
            if 0 <= c < W:
                v = 0.0
                for k in range(oy.size):
                    r = i + oy[k]
                    term = wy[k] * (np.float64(a[r, c]) if 0 <= r < H else np.nan)
                    v = term if k == 0 else v + term
            else:
                v = np.nan
            term = wx[m] * v
            acc = term if m == 0 else acc + term
        out[n] = acc
