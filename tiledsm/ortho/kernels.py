"""Interpolation kernels of orthorectification: NN, BL, CR, CS (numba).

The four resamplers of the UAV multi-image SR method: nearest neighbour
(NN), bilinear (BL) and two cubic convolutions (Keys 1981, IEEE TASSP
29(6) 1153-1160) with the weight function

.. math::

    w(t) = (a+2)|t|^3 - (a+3)|t|^2 + 1         \\quad |t| \\le 1
    w(t) = a|t|^3 - 5a|t|^2 + 8a|t| - 4a       \\quad 1 < |t| \\le 2
    w(t) = 0                                   \\quad |t| > 2

after Rifman (CR, ``a = -1``) and Simon (CS, ``a = -0.5``). OpenCV's cubic
uses ``a = -0.75``, so CR and CS are computed here.

Conventions
-----------
- Sample positions are GDAL pixel coordinates ``(row, col)``: the top-left
  image corner is ``(0, 0)`` and array element ``[i, j]`` covers
  ``[i, i+1) x [j, j+1)`` with its centre at ``(i+.5, j+.5)``. (OpenCV's
  ``remap`` puts the centre at ``(i, j)``: ``cv2 = GDAL - 0.5``.)
- Points outside the image extent ``[0, rows] x [0, cols]`` are NaN.
  Inside it, the kernel support is clamped to the image (border pixels
  replicated, OpenCV's ``BORDER_REPLICATE``).
- Any NaN pixel with a non-zero weight makes the sample NaN.
- A window of the image may stand for the whole image (``origin``,
  ``shape``): the result is the same as on the whole image as long as the
  window holds the support of every point (``radius`` pixels around it),
  which is what makes tiled orthorectification exact.

The kernels live in :data:`KERNELS` (explicit registrations, duplicates
refused); :func:`get_kernel` resolves a name, :func:`known_kernel` checks one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from tiledsm.errors import InvalidOptionError

__all__ = ["Kernel", "KERNELS", "register_kernel", "known_kernel", "get_kernel", "cubic_weight", "sample"]

# kernel families understood by the numba sampler
_NEAREST, _LINEAR, _CUBIC = 0, 1, 2


@dataclass(frozen=True)
class Kernel:
    """An interpolation kernel.

    Attributes
    ----------
    name : str
        Registry name (``"nn"``, ``"bl"``, ``"cr"``, ``"cs"``).
    family : int
        0 nearest, 1 linear, 2 cubic convolution.
    a : float
        Cubic convolution parameter (ignored by the other families).
    label : str
        Name in the method's tables (``"NN"``, ``"BL"``, ``"CR"``, ``"CS"``).
    """

    name: str
    family: int
    a: float = 0.0
    label: str = ""

    @property
    def radius(self) -> int:
        """Support half-width, pixels: the margin a window needs around
        the sampled points (1 for NN and BL, 2 for cubics)."""
        return 2 if self.family == _CUBIC else 1


#: name -> kernel
KERNELS: dict[str, Kernel] = {}


def register_kernel(kernel: Kernel) -> Kernel:
    """Add a kernel to :data:`KERNELS` (a duplicate name is refused)."""
    if kernel.name in KERNELS:
        raise ValueError(f"interpolation kernel {kernel.name!r} registered twice")
    if kernel.family not in (_NEAREST, _LINEAR, _CUBIC):
        raise ValueError(f"interpolation kernel {kernel.name!r}: unknown family {kernel.family}")
    KERNELS[kernel.name] = kernel
    return kernel


register_kernel(Kernel("nn", _NEAREST, label="NN"))
register_kernel(Kernel("bl", _LINEAR, label="BL"))
register_kernel(Kernel("cr", _CUBIC, a=-1.0, label="CR"))
register_kernel(Kernel("cs", _CUBIC, a=-0.5, label="CS"))


def known_kernel(name: str) -> str:
    """``name``, unchanged, when it names a registered kernel (any case):
    the validator of a model's kernel field (the model reports the error
    at the field, :data:`tiledsm.ortho.recipe.KernelName`).

    Raises
    ------
    ValueError
        Unknown name; the message lists the known kernels.
    """
    if str(name).lower() not in KERNELS:
        raise ValueError(f"unknown interpolation kernel {name!r}; known: {sorted(KERNELS)}")
    return name


def get_kernel(name: str | Kernel, field: str = "kernel") -> Kernel:
    """The registered kernel called ``name`` (case-insensitive).

    Raises
    ------
    InvalidOptionError
        Unknown name; the message names ``field`` and the known kernels.
    """
    if isinstance(name, Kernel):
        return name
    try:
        return KERNELS[known_kernel(str(name)).lower()]
    except ValueError as exc:
        raise InvalidOptionError(f"{field}: {exc}") from None


@numba.njit(nogil=True, cache=True, inline="always")
def cubic_weight(t: float, a: float) -> float:
    """Cubic convolution weight ``w(t)`` with parameter ``a`` (module docstring)."""
    t = abs(t)
    if t <= 1.0:
        return ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0
    if t <= 2.0:
        return ((a * t - 5.0 * a) * t + 8.0 * a) * t - 4.0 * a
    return 0.0


@numba.njit(nogil=True, cache=True)
def _sample(img, rows, cols, r0, c0, nrows, ncols, family, a, out):
    """``out[k] = interpolation of img at (rows[k], cols[k])`` (GDAL
    coordinates of the whole image; ``img`` is the window whose element
    ``[0, 0]`` is image pixel ``[r0, c0]``; ``nrows x ncols`` the image)."""
    h, w = img.shape
    wr = np.empty(4)
    wc = np.empty(4)
    for k in range(rows.size):
        r = rows[k]
        c = cols[k]
        if not (r >= 0.0 and r <= nrows and c >= 0.0 and c <= ncols):
            out[k] = np.nan
            continue
        if family == 0:
            i = min(int(math.floor(r)), nrows - 1) - r0
            j = min(int(math.floor(c)), ncols - 1) - c0
            i = min(max(i, 0), h - 1)
            j = min(max(j, 0), w - 1)
            out[k] = img[i, j]
            continue
        # array-index coordinates (pixel centres at integers)
        y = r - 0.5
        x = c - 0.5
        iy = int(math.floor(y))
        ix = int(math.floor(x))
        fy = y - iy
        fx = x - ix
        if family == 1:
            n = 2
            lo = 0
            wr[0] = 1.0 - fy
            wr[1] = fy
            wc[0] = 1.0 - fx
            wc[1] = fx
        else:
            n = 4
            lo = -1
            for m in range(4):
                wr[m] = cubic_weight(fy - (m - 1), a)
                wc[m] = cubic_weight(fx - (m - 1), a)
        acc = 0.0
        for m in range(n):
            if wr[m] == 0.0:
                continue
            ii = min(max(iy + lo + m, 0), nrows - 1) - r0
            ii = min(max(ii, 0), h - 1)
            row_acc = 0.0
            for q in range(n):
                if wc[q] == 0.0:
                    continue
                jj = min(max(ix + lo + q, 0), ncols - 1) - c0
                jj = min(max(jj, 0), w - 1)
                row_acc += wc[q] * img[ii, jj]
            acc += wr[m] * row_acc
        out[k] = acc


def sample(
    image: np.ndarray,
    rows,
    cols,
    kernel: str | Kernel = "bl",
    *,
    origin: tuple[int, int] = (0, 0),
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Interpolate an image at arbitrary points.

    Parameters
    ----------
    image : numpy.ndarray
        ``(h, w)`` pixels (any real dtype), NaN for nodata; the whole image,
        or the window of it whose element ``[0, 0]`` is pixel ``origin``.
    rows, cols : array_like
        GDAL pixel coordinates of the whole image (module conventions),
        broadcast together.
    kernel : str or Kernel
        ``"nn"``, ``"bl"``, ``"cr"``, ``"cs"`` or any registered kernel.
    origin : (int, int)
        Image pixel of ``image[0, 0]``.
    shape : (int, int), optional
        Size of the whole image (default: ``image.shape``, with ``origin``
        ``(0, 0)``).

    Returns
    -------
    numpy.ndarray
        float32 samples, the broadcast shape of ``rows`` and ``cols``; NaN
        outside the image or where the support holds NaN.
    """
    k = get_kernel(kernel)
    img = np.ascontiguousarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"sample: expected a 2-D image, got shape {img.shape}")
    r, c = np.broadcast_arrays(np.asarray(rows, np.float64), np.asarray(cols, np.float64))
    nrows, ncols = (img.shape if shape is None else (int(shape[0]), int(shape[1])))
    out = np.empty(r.size, np.float64)
    _sample(img, np.ascontiguousarray(r).ravel(), np.ascontiguousarray(c).ravel(), int(origin[0]), int(origin[1]),
            nrows, ncols, k.family, float(k.a), out)
    return out.reshape(r.shape).astype(np.float32)
