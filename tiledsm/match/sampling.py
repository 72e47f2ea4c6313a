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
    "CUBIC_A", "keys", "keys_near", "keys_far", "row4", "lattice_cell", "height_segment", "lattice_segment",
    "trilinear", "cubic_weights", "cubic_sum", "cubic_at", "interpolate", "sample_view",
]

#: Keys' cubic convolution parameter (OpenCV's INTER_CUBIC uses the same)
CUBIC_A = -0.75


@nb.njit(nogil=True, cache=True, inline="always")
def keys(d, a):
    """Keys' cubic convolution kernel at distance ``d >= 0``."""
    if d <= 1.0:
        return ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0
    if d < 2.0:
        return ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a
    return 0.0


@nb.njit(nogil=True, cache=True, inline="always")
def keys_near(d, a):
    """:func:`keys` for ``0 <= d <= 1``."""
    return ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0


@nb.njit(nogil=True, cache=True, inline="always")
def keys_far(d, a):
    """:func:`keys` for ``1 <= d <= 2``."""
    return ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a


@nb.njit(nogil=True, cache=True, inline="always")
def row4(img, r, ix, w0, w1, w2, w3):
    """``w0 img[r, ix - 1] + .. + w3 img[r, ix + 2]``, summed left to right."""
    row = w0 * img[r, ix - 1]
    row += w1 * img[r, ix]
    row += w2 * img[r, ix + 1]
    row += w3 * img[r, ix + 2]
    return row


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


@nb.njit(nogil=True, cache=True, inline="always")
def cubic_weights(f):
    """The four Keys (a = -0.75) weights of the pixels at distances ``f +
    1, f, 1 - f, 2 - f`` from a position ``f`` past a pixel, ``0 <= f <
    1``.

    Each by the branch of :func:`keys` its distance falls in, without the
    branches: both branches give exactly 0 at d = 1 and the far one
    exactly 0 at d = 2 for a = -0.75, so the values are those of
    :func:`keys`."""
    return (keys_far(f + 1.0, CUBIC_A), keys_near(f, CUBIC_A), keys_near(1.0 - f, CUBIC_A),
            keys_far(2.0 - f, CUBIC_A))


@nb.njit(nogil=True, cache=True, inline="always")
def cubic_sum(img, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3):
    """``sum_r wy_r * row4(img, iy - 1 + r, ix, wx)``, rows top to bottom:
    the bicubic value at a pixel and the weights of its fractions
    (:func:`cubic_weights`), the 4 x 4 support inside the image
    (unchecked)."""
    acc = 0.0
    acc += wy0 * row4(img, iy - 1, ix, wx0, wx1, wx2, wx3)
    acc += wy1 * row4(img, iy, ix, wx0, wx1, wx2, wx3)
    acc += wy2 * row4(img, iy + 1, ix, wx0, wx1, wx2, wx3)
    acc += wy3 * row4(img, iy + 2, ix, wx0, wx1, wx2, wx3)
    return acc


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
