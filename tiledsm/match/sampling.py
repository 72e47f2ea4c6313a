"""Image sampling at the projections of ground cells (SGVLL matching).

The pieces shared by the two sweeps of :mod:`tiledsm.match.sgvll`: the
sparse projection lattice lookup (:func:`lattice_cell`, :func:`trilinear`),
the image interpolation (:func:`interpolate`: bicubic after Keys, a =
-0.75, as OpenCV's ``INTER_CUBIC``, or bilinear), and the plain per-height
sampler of the reference sweep (:func:`sample_view`). The compiled sweep
(:mod:`tiledsm.match.sweep`) calls the same functions, so both give the
same samples bit for bit.

Conventions: image coordinates are in the array-index convention (pixel
centre ``[i, j]`` at ``(i, j)``: GDAL's coordinates minus 0.5) of the
image *window* passed; NaN marks nodata, and a sample whose support leaves
the window or touches NaN is NaN.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = [
    "CUBIC_A", "lattice_cell", "height_segment", "lattice_segment",
    "trilinear", "cubic_weights", "column4", "cubic_sum", "cubic_at", "interpolate", "sample_view",
]

#: Keys' cubic convolution parameter (OpenCV's INTER_CUBIC uses the same)
CUBIC_A = -0.75


@nb.njit(nogil=True, cache=True, inline="always")
def lattice_cell(g, stride, n0, n):
    """Lattice interval ``k`` (clamped to ``[.., n - 2]``) and fraction of
    global cell ``g`` on nodes every ``stride`` cells starting at node ``n0``."""
    u = g / stride
    k = int(np.floor(u))
    f = u - k
    k -= n0
    if k > n - 2:
        k = n - 2
        f = u - (k + n0)
    return k, f


@nb.njit(nogil=True, cache=True, inline="always")
def height_segment(h, dh, k0, nh):
    """Interval ``t0`` (clamped to ``[0, nh - 2]``) of the height lattice
    ``(k0 + t) * dh`` holding height ``h``, and the fraction of ``h`` in it
    (beyond the lattice: extrapolated from the end interval)."""
    return lattice_segment(h / dh, k0, nh)


@nb.njit(nogil=True, cache=True, inline="always")
def lattice_segment(tt, k0, nh):
    """:func:`height_segment` of a height given in lattice steps, ``tt =
    h / dh`` (a sweep divides all its heights first, in one vectorised
    loop)."""
    kt = int(np.floor(tt))
    ft = tt - kt
    t0 = kt - k0
    if t0 < 0:
        t0 = 0
        ft = tt - k0
    elif t0 > nh - 2:
        t0 = nh - 2
        ft = tt - (k0 + t0)
    return t0, ft


@nb.njit(nogil=True, cache=True)
def sample_view(
    img, lat_r, lat_c, stride, k0, dh, href, offset, gi0, gj0, n0i, n0j, win_r, win_c, cubic, r0, r1, c0, c1, out
):
    """Sample one view at the projections of block cells ``[r0:r1, c0:c1]``
    at heights ``href + offset``; writes ``out[:r1-r0, :c1-c0]``.

    Image coordinates come from trilinear interpolation of the sparse
    projection lattice ``(nh, gy, gx)`` of full-image pixel coordinates in
    the array-index convention (``row - 0.5``, ``col - 0.5``) at ground
    nodes on *global* cell indices ``(n0i + a) * stride``,
    ``(n0j + b) * stride`` and heights ``(k0 + t) * dh``; block cell
    ``[i, j]`` is global cell ``[gi0 + i, gj0 + j]``. Everything is indexed
    globally and the window origin ``(win_r, win_c)`` is subtracted last
    (exactly), so a cell's sample is bit-identical in every block that
    contains it. Interpolation is bicubic (Keys, a = -0.75) or bilinear; a
    sample whose support leaves the window, or touches NaN, is NaN.
    """
    nh, gy, gx = lat_r.shape
    h, w = img.shape
    # the lattice column of every block column, once (not once per row)
    jcol = np.empty(c1 - c0, np.int64)
    fcol = np.empty(c1 - c0, np.float64)
    for j in range(c0, c1):
        jcol[j - c0], fcol[j - c0] = lattice_cell(gj0 + j, stride, n0j, gx)
    for i in range(r0, r1):
        i0, fy = lattice_cell(gi0 + i, stride, n0i, gy)
        for j in range(c0, c1):
            j0 = jcol[j - c0]
            fx = fcol[j - c0]
            t0, ft = height_segment(href[i, j] + offset, dh, k0, nh)
            y = trilinear(lat_r, t0, i0, j0, ft, fy, fx) - win_r
            x = trilinear(lat_c, t0, i0, j0, ft, fy, fx) - win_c
            out[i - r0, j - c0] = interpolate(img, y, x, cubic, h, w)


@nb.njit(nogil=True, cache=True, inline="always")
def trilinear(lat, t0, i0, j0, ft, fy, fx):
    """Trilinear interpolation of ``lat[t, i, j]`` at ``(t0 + ft, i0 + fy,
    j0 + fx)``: bilinear on the two height planes, then linear in height."""
    w00 = (1 - fy) * (1 - fx)
    w01 = (1 - fy) * fx
    w10 = fy * (1 - fx)
    w11 = fy * fx
    a = w00 * lat[t0, i0, j0] + w01 * lat[t0, i0, j0 + 1] + w10 * lat[t0, i0 + 1, j0] + w11 * lat[t0, i0 + 1, j0 + 1]
    b = (
        w00 * lat[t0 + 1, i0, j0] + w01 * lat[t0 + 1, i0, j0 + 1]
        + w10 * lat[t0 + 1, i0 + 1, j0] + w11 * lat[t0 + 1, i0 + 1, j0 + 1]
    )
    return a + ft * (b - a)


# Keys' kernel (a = -0.75) in float32: the samples are float32 (the cost
# volume's type), and GPUs run float32 arithmetic faster than float64
_ONE = np.float32(1.0)
_A = np.float32(CUBIC_A)
_A2 = np.float32(CUBIC_A + 2.0)


@nb.njit(nogil=True, cache=True, inline="always")
def cubic_weights(f):
    """The four Keys (a = -0.75) weights, float32, of the pixels at
    distances ``f + 1, f, 1 - f, 2 - f`` from a position ``f`` past a
    pixel, ``0 <= f < 1`` (rounded to float32 first).

    Keys' kernel (``(a + 2) d^3 - (a + 3) d^2 + 1`` for ``d <= 1``, ``a
    d^3 - 5 a d^2 + 8 a d - 4 a`` for ``1 <= d < 2``) in factored form,
    with ``g = 1 - f``: the far one
    ``a d^3 - 5 a d^2 + 8 a d - 4 a = a (d - 1) (d - 2)^2`` gives ``a f
    g^2`` and ``a g f^2``, the near one ``(a + 2) d^3 - (a + 3) d^2 + 1 =
    (d - 1) ((a + 2) d^2 - d - 1)`` gives ``g (1 + f - (a + 2) f^2)`` and
    ``f (1 + g - (a + 2) g^2)``. Expanded, the far weights near ``d = 2``
    are differences of terms near 3 that cancel (errors of 1e-6 on weights
    of 1e-6 in float32); factored, each weight is exact to a few ulps of
    itself, and exactly ``(0, 1, 0, 0)`` at ``f = 0``."""
    t = np.float32(f)
    g = _ONE - t
    return ((_A * t) * (g * g), g * ((_ONE + t) - (_A2 * t) * t), t * ((_ONE + g) - (_A2 * g) * g),
            (_A * g) * (t * t))


@nb.njit(nogil=True, cache=True, inline="always")
def column4(img, iy, c, wy0, wy1, wy2, wy3):
    """``wy0 img[iy - 1, c] + .. + wy3 img[iy + 2, c]``, summed top to
    bottom (float32 image and weights: float32)."""
    return ((wy0 * img[iy - 1, c] + wy1 * img[iy, c]) + wy2 * img[iy + 1, c]) + wy3 * img[iy + 2, c]


@nb.njit(nogil=True, cache=True, inline="always")
def cubic_sum(img, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3):
    """The bicubic value at pixel ``(iy, ix)`` and the weights of its
    fractions (:func:`cubic_weights`), the 4 x 4 support inside the image
    (unchecked), float32: each of the four columns summed top to bottom
    (:func:`column4`), then ``(wx0 c0 + wx2 c2) + (wx1 c1 + wx3 c3)``.

    The order is chosen for the vector units: the four columns are one
    4-lane vector of each row's four contiguous pixels, and the last sum
    is the halving tree of a vector's lanes. With the float32 weights, a
    level-0 task's interpolation took 11-12 ns per sample against 14-19
    in float64 summed row by row (``benchmarks/kernel_parts.py`` run in
    turns on both versions; docs: changelog, "Bicubic samples in
    float32")."""
    c = ix - 1
    c0 = column4(img, iy, c, wy0, wy1, wy2, wy3)
    c1 = column4(img, iy, c + 1, wy0, wy1, wy2, wy3)
    c2 = column4(img, iy, c + 2, wy0, wy1, wy2, wy3)
    c3 = column4(img, iy, c + 3, wy0, wy1, wy2, wy3)
    return (wx0 * c0 + wx2 * c2) + (wx1 * c1 + wx3 * c3)


@nb.njit(nogil=True, cache=True, inline="always")
def cubic_at(img, iy, ix, fy, fx):
    """Bicubic (Keys, a = -0.75) value of ``img`` at ``(iy + fy, ix + fx)``,
    ``0 <= fy, fx < 1``, the 4 x 4 support inside the image (unchecked)."""
    wy0, wy1, wy2, wy3 = cubic_weights(fy)
    wx0, wx1, wx2, wx3 = cubic_weights(fx)
    return cubic_sum(img, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)


@nb.njit(nogil=True, cache=True, inline="always")
def interpolate(img, y, x, cubic, h, w):
    """``img`` (``h x w``) at ``(y, x)`` (array-index convention): bicubic
    (Keys, a = -0.75) when ``cubic`` else bilinear; NaN when the support
    leaves the image or touches NaN, or the position is not finite."""
    if not (np.isfinite(y) and np.isfinite(x)):
        return np.nan
    iy = int(np.floor(y))
    ix = int(np.floor(x))
    fy = y - iy
    fx = x - ix
    if cubic:
        if iy < 1 or ix < 1 or iy + 2 >= h or ix + 2 >= w:
            return np.nan
        return cubic_at(img, iy, ix, fy, fx)
    if iy < 0 or ix < 0 or iy + 1 >= h or ix + 1 >= w:
        return np.nan
    top = img[iy, ix] + fx * (img[iy, ix + 1] - img[iy, ix])
    bot = img[iy + 1, ix] + fx * (img[iy + 1, ix + 1] - img[iy + 1, ix])
    return top + fy * (bot - top)
