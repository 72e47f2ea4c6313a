"""Coarse to fine: image pyramids and the search band a coarser DSM gives
the next finer level.

Pyramid level ``L`` matches images downsampled by ``f = 2**L`` on a ground
grid of cells ``f`` times larger that shares the top-left corner of the
full-resolution grid, so coarse cell ``[I, J]`` covers finer cells
``[2I : 2I+2, 2J : 2J+2]`` of the next level.

Everything here is a pure function of a block *and a halo whose depth is
stated* (:func:`search_halo`): computed on any block of a chunked array
with that halo, the result on the block's core equals the result on the
whole array, bit for bit. This is what makes the tiled DSM independent of
its chunking.

Conventions: heights in metres (ellipsoidal), NaN = no height; image
arrays float32 with NaN nodata; downsampled pixel ``[i, j]`` covers pixels
``[f*i : f*(i+1), f*j : f*(j+1)]`` (GDAL coordinates scale by ``1/f``,
:meth:`tiledsm.geometry.RPC.scaled`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from pydantic import Field, field_validator
from scipy import ndimage

from tiledsm.errors import MatchingError
from tiledsm.spec import StrictModel, not_below

__all__ = ["SearchParams", "downsample", "search_halo", "search_from_coarse"]


class SearchParams(StrictModel):
    """How a coarser DSM becomes the search band of the next finer level.

    Attributes
    ----------
    smooth : float
        Gaussian sigma (coarse cells) of the NaN-aware smoothing that turns
        the coarser heights into the reference surface ``h_ref``.
    fill_sigma : float
        Gaussian sigma (coarse cells) of the wider NaN-aware average used
        where no coarser height lies within the ``smooth`` support (holes).
        Cells farther than its support from any coarser height are not
        searched (NaN): the coarser level found nothing around them.
    truncate : float
        Both Gaussians are cut at ``truncate * sigma`` (the halo depth).
    hole_factor : float
        The band is ``hole_factor`` times wider where the coarser cell
        itself had no height.
    relative_labels : bool
        Candidate heights of the finer level on the lattice ``h_ref + k *
        step`` (labels relative to the reference surface: the semi-global
        penalties then count steps away from a surface parallel to the
        smoothed coarser DSM) or on the scene-wide lattice ``k * step``
        (absolute labels, the default: penalties count height changes, as
        at a single level; the band is the same). Neighbouring cells' bands
        are then shifted against each other; the aggregation leaves out the
        candidates a cell does not have (``nvalid`` of
        :func:`tiledsm.match.sgm.aggregate`), so the result is the same in
        every chunking. On ``s2p_pair`` at 2 levels, absolute labels keep
        the single level's NMAD where relative ones lose 0.014 m
        (``benchmarks/dsm_search.py``, ``benchmarks/blunders.py``).
    """

    smooth: float = Field(1.0, gt=0, description="Gaussian sigma of the smoothing into the reference surface, "
                          "coarse cells")
    fill_sigma: float = Field(4.0, validate_default=True, description="Gaussian sigma of the wider average filling holes, coarse cells "
                              "(>= smooth)")
    truncate: float = Field(3.0, gt=0, description="both Gaussians are cut at truncate * sigma")
    hole_factor: float = Field(3.0, ge=1, description="the band is this many times wider where the coarser cell "
                               "had no height")
    relative_labels: bool = Field(False, description="candidate heights on h_ref + k * step (relative labels) "
                                  "instead of the scene-wide lattice k * step")

    _fill_wider = field_validator("fill_sigma")(not_below("smooth"))


def downsample(img: np.ndarray, factor: int) -> np.ndarray:
    """Area-average downsampling by an integer factor, NaN-aware.

    An output pixel is NaN if any input pixel of its block is NaN. Output
    pixel ``[i, j]`` covers input pixels ``[f*i:f*(i+1), f*j:f*(j+1)]``;
    trailing rows/columns that do not fill a block are dropped. A window
    read at a row/column that is a multiple of ``factor`` downsamples to
    exactly the pixels of the whole downsampled image.
    """
    img = np.asarray(img, np.float32)
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    if h == 0 or w == 0:
        raise MatchingError(f"image window {img.shape} too small to downsample by {factor}")
    a = img[: h * factor, : w * factor]
    # the f*f pixels of a block summed in one fixed order (NaN propagates):
    # every output pixel is the same arithmetic wherever the window starts
    # (OpenCV's area resize is not: its vectorised body and scalar tail
    # round differently)
    acc = np.zeros((h, w), np.float64)
    for di in range(factor):
        for dj in range(factor):
            acc += a[di::factor, dj::factor]
    return (acc / (factor * factor)).astype(np.float32)


def _radius(sigma: float, truncate: float) -> int:
    # scipy.ndimage.gaussian_filter's kernel radius
    return int(truncate * float(sigma) + 0.5)


def search_halo(params: SearchParams = SearchParams()) -> int:
    """Halo (coarse cells) that :func:`search_from_coarse` needs around a
    block: the wider Gaussian's radius plus one cell of bilinear support."""
    return _radius(params.fill_sigma, params.truncate) + 1


def _nan_mean(values: np.ndarray, valid: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Gaussian-weighted mean of the valid values (NaN where the kernel
    holds none). Cells beyond the array count as invalid."""
    num = ndimage.gaussian_filter(np.where(valid, values, 0.0), sigma, mode="constant", cval=0.0, truncate=truncate)
    den = ndimage.gaussian_filter(valid.astype(np.float64), sigma, mode="constant", cval=0.0, truncate=truncate)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-9, num / den, np.nan)


def search_from_coarse(
    coarse: np.ndarray,
    depth: int,
    margin: float,
    h_range: tuple[float, float],
    params: SearchParams = SearchParams(),
) -> np.ndarray:
    """Reference surface and search band of a finer level from a block of
    the coarser level's heights.

    The coarser heights are smoothed (NaN-aware Gaussian, ``smooth``), holes
    filled by a wider NaN-aware Gaussian (``fill_sigma``), and interpolated
    bilinearly (NaN-aware) to the centres of the finer cells: the reference
    surface ``h_ref``. A finer cell searches ``h_ref ± margin``
    (``± hole_factor * margin`` where the coarser cell under it had no
    height), clipped to ``h_range``.

    Parameters
    ----------
    coarse : numpy.ndarray
        ``(ny + 2 depth, nx + 2 depth)`` coarser heights (metres, NaN = none)
        of a block and its halo; cells beyond the grid are NaN.
    depth : int
        Halo width, coarse cells; at least :func:`search_halo` of
        ``params`` for the result to equal the whole-grid result.
    margin : float
        Half-width of the band, metres (a few finer height steps).
    h_range : (float, float)
        The scene's height range, metres.
    params : SearchParams

    Returns
    -------
    numpy.ndarray
        ``(3, 2 ny, 2 nx)`` float32: ``h_ref``, ``lo``, ``hi`` of the finer
        cells covered by the block's core. NaN in all three where no
        coarser height lies within the fill support (not searched).
    """
    need = search_halo(params)
    if depth < need:
        raise MatchingError(f"search_from_coarse: halo {depth} < {need} coarse cells needed by {params}")
    c = np.asarray(coarse, np.float64)
    valid = np.isfinite(c)
    ny, nx = c.shape[0] - 2 * depth, c.shape[1] - 2 * depth
    # the smoothing over the cells _band reads grown by its radius: their
    # values are the whole window's bit for bit (see _fill_holes); the
    # halo beyond serves the wider mean only
    r = _radius(params.smooth, params.truncate)
    a0, a1 = max(depth - 1 - r, 0), min(depth + ny + 1 + r, c.shape[0])
    b0, b1 = max(depth - 1 - r, 0), min(depth + nx + 1 + r, c.shape[1])
    ref = np.full(c.shape, np.nan)
    ref[a0:a1, b0:b1] = _nan_mean(c[a0:a1, b0:b1], valid[a0:a1, b0:b1], params.smooth, params.truncate)
    _fill_holes(ref, c, valid, depth, ny, nx, params)
    out = np.empty((3, 2 * ny, 2 * nx), np.float32)
    _band(ref, valid, depth, float(margin), float(params.hole_factor), float(h_range[0]), float(h_range[1]), out)
    return out


def _fill_holes(ref: np.ndarray, c: np.ndarray, valid: np.ndarray, depth: int, ny: int, nx: int,
                params: SearchParams) -> None:
    """Fill in place the NaN cells of ``ref`` that :func:`_band` reads (the
    core's coarse cells and one around) with the wider NaN-aware mean of
    ``c`` (``fill_sigma``).

    The wider mean is computed only over the holes' bounding box grown by
    its kernel radius: each value inside the box has its whole support in
    that crop, and the filter's arithmetic does not depend on where a
    cell sits, so the values are those of the whole window's filter bit
    for bit (``tests/match/test_sgvll.py``) at a fraction of its cost
    where the holes are few (its kernel has 25 taps per axis with the
    default parameters, the smoothing's 7; ``benchmarks/search_band.py``)."""
    a0, a1 = max(depth - 1, 0), min(depth + ny + 1, ref.shape[0])
    b0, b1 = max(depth - 1, 0), min(depth + nx + 1, ref.shape[1])
    holes = np.isnan(ref[a0:a1, b0:b1])
    if not holes.any():
        return
    rows = np.flatnonzero(holes.any(axis=1))
    cols = np.flatnonzero(holes.any(axis=0))
    i0, i1 = a0 + int(rows[0]), a0 + int(rows[-1]) + 1
    j0, j1 = b0 + int(cols[0]), b0 + int(cols[-1]) + 1
    r = _radius(params.fill_sigma, params.truncate)
    # the crop ends at the window's edges where the support reaches them:
    # there the filter's constant-zero border is the window's own
    y0, y1 = max(i0 - r, 0), min(i1 + r, ref.shape[0])
    x0, x1 = max(j0 - r, 0), min(j1 + r, ref.shape[1])
    fill = _nan_mean(c[y0:y1, x0:x1], valid[y0:y1, x0:x1], params.fill_sigma, params.truncate)
    box = ref[i0:i1, j0:j1]
    box[...] = np.where(np.isfinite(box), box, fill[i0 - y0 : i1 - y0, j0 - x0 : j1 - x0])


@nb.njit(nogil=True, cache=True)
def _band(ref, valid, depth, margin, hole_factor, lo_r, hi_r, out):
    """``out[:, a, b]``: ``h_ref``, ``lo``, ``hi`` of finer cell ``[a, b]``
    of the core (see :func:`search_from_coarse`): the NaN-aware bilinear
    interpolation of ``ref`` (its corners added in a fixed order), the
    band ``± margin`` (``± hole_factor * margin`` next to a coarser cell
    without a height) clipped to ``[lo_r, hi_r]``; NaN where nothing is
    searched."""
    _, h2, w2 = out.shape
    nan = np.float32(np.nan)
    # finer cell a of the core sits at coarse coordinate (a + 0.5) / 2 - 0.5
    # from the core's first cell: between coarse cells floor(u) and floor(u) + 1
    # (the columns' once, not once per row)
    jcol = np.empty(w2, np.int64)
    fcol = np.empty(w2, np.float64)
    for b in range(w2):
        v = (b + 0.5) / 2 - 0.5 + depth
        jcol[b] = int(np.floor(v))
        fcol[b] = v - jcol[b]
    for a in range(h2):
        u = (a + 0.5) / 2 - 0.5 + depth
        i0 = int(np.floor(u))
        fy = u - i0
        for b in range(w2):
            j0 = jcol[b]
            fx = fcol[b]
            num = 0.0
            den = 0.0
            hole = False
            for di in range(2):
                wy = 1 - fy if di == 0 else fy
                for dj in range(2):
                    wx = 1 - fx if dj == 0 else fx
                    w = wy * wx
                    val = ref[i0 + di, j0 + dj]
                    if np.isfinite(val) and w > 0:
                        num += w * val
                        den += w
                    if w > 0 and not valid[i0 + di, j0 + dj]:
                        hole = True
            href = num / den if den > 1e-12 else np.nan
            m = hole_factor * margin if hole else margin
            lo = min(max(href - m, lo_r), hi_r)
            hi = min(max(href + m, lo_r), hi_r)
            if not np.isfinite(href) or not hi > lo:
                out[0, a, b] = nan
                out[1, a, b] = nan
                out[2, a, b] = nan
                continue
            out[0, a, b] = min(max(href, lo_r), hi_r)
            out[1, a, b] = lo
            out[2, a, b] = hi


def level_shape(shape: tuple[int, int], level: int) -> tuple[int, int]:
    """Shape of pyramid level ``level`` of a grid of ``shape`` cells."""
    f = 2**level
    return (max(1, math.ceil(shape[0] / f)), max(1, math.ceil(shape[1] / f)))
