"""Image-space disparity of a rectified pair with the same cost and
aggregation as the object-space matcher: a test helper that validates
them on Middlebury (``test_stereo.py``), not part of the package.

Conventions
-----------
- Rectified pair, rows are epipolar lines; disparity ``d`` maps left pixel
  ``(y, x)`` to right pixel ``(y, x - d)`` (``x_right = x_left - d``),
  in pixels.
- Images are 2-D arrays (any numeric dtype); NaN = nodata.
- Output disparities are float32, NaN where rejected (left-right check,
  ZNCC threshold, speckles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from tiledsm.match.cost import zncc_cost
from tiledsm.match.sgm import aggregate, remove_speckles, winner_take_all

__all__ = ["StereoParams", "cost_volume", "disparity", "fill_occlusions"]


@dataclass(frozen=True)
class StereoParams:
    """Parameters of :func:`disparity`.

    Attributes
    ----------
    window : int
        ZNCC window side (odd), pixels.
    P1, P2 : float
        SGM penalties in cost units (cost = 1 - ZNCC, 0..2).
    p2_gamma : float or None
        Intensity difference (image units) halving ``P2`` across edges
        (adaptive P2, guided by the left image); ``None`` = constant P2.
    lr_max_diff : float
        Left-right consistency tolerance, pixels.
    zncc_min : float
        Cells whose winning ZNCC is below this are rejected.
    speckle_size, speckle_diff : int, float
        Components smaller than ``speckle_size`` pixels (neighbours within
        ``speckle_diff`` px) are removed.
    """

    window: int = 5
    P1: float = 0.1
    P2: float = 1.0
    p2_gamma: float | None = 10.0
    lr_max_diff: float = 1.0
    zncc_min: float = -1.0
    speckle_size: int = 50
    speckle_diff: float = 1.0

    def __post_init__(self) -> None:
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"StereoParams.window must be odd and >= 1, got {self.window}")
        if not 0 <= self.P1 <= self.P2:
            raise ValueError(f"StereoParams: need 0 <= P1 <= P2, got P1={self.P1}, P2={self.P2}")


def cost_volume(left: np.ndarray, right: np.ndarray, d_min: int, d_max: int, window: int) -> np.ndarray:
    """ZNCC cost volume ``(ny, nx, d_max - d_min + 1)`` (float32, NaN invalid);
    candidate ``k`` is disparity ``d_min + k``."""
    left = np.asarray(left, np.float32)
    right = np.asarray(right, np.float32)
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError(f"cost_volume: images must be 2-D and of equal shape, got {left.shape}, {right.shape}")
    if d_max < d_min:
        raise ValueError(f"cost_volume: empty disparity range [{d_min}, {d_max}]")
    ny, nx = left.shape
    nd = d_max - d_min + 1
    vol = np.empty((ny, nx, nd), np.float32)
    shifted = np.empty_like(right)
    for k in range(nd):
        d = d_min + k
        shifted.fill(np.nan)
        # shifted[:, x] = right[:, x - d]
        if d >= 0:
            if d < nx:
                shifted[:, d:] = right[:, : nx - d]
        elif -d < nx:
            shifted[:, : nx + d] = right[:, -d:]
        zncc_cost(left, shifted, window // 2, out=vol[:, :, k])
    return vol


@nb.njit(nogil=True, cache=True)
def _right_disparity(S, d_min):
    """Right-image WTA disparity from the left-referenced volume:
    ``d_R(x_r) = argmin_d S(x_r + d, d)``."""
    ny, nx, nd = S.shape
    out = np.full((ny, nx), np.nan, np.float32)
    for i in range(ny):
        for xr in range(nx):
            best = np.float32(3.0e38)
            kb = -1
            for k in range(nd):
                x = xr + d_min + k
                if 0 <= x < nx:
                    v = S[i, x, k]
                    if v < best:
                        best = v
                        kb = k
            if kb >= 0:
                out[i, xr] = d_min + kb
    return out


@nb.njit(nogil=True, cache=True)
def _lr_check(dl, dr, tol):
    ny, nx = dl.shape
    out = dl.copy()
    for i in range(ny):
        for x in range(nx):
            d = dl[i, x]
            if not np.isfinite(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr < 0 or xr >= nx or not np.isfinite(dr[i, xr]) or abs(dr[i, xr] - d) > tol:
                out[i, x] = np.nan
    return out


def disparity(
    left: np.ndarray, right: np.ndarray, d_min: int, d_max: int, params: StereoParams = StereoParams()
) -> tuple[np.ndarray, np.ndarray]:
    """Dense disparity of a rectified pair (ZNCC + 8-path SGM + WTA).

    Parameters
    ----------
    left, right : numpy.ndarray
        Rectified images, same shape; NaN = nodata.
    d_min, d_max : int
        Disparity search range, pixels (``x_right = x_left - d``).
    params : StereoParams

    Returns
    -------
    disp : numpy.ndarray
        ``(ny, nx)`` float32 left disparity (sub-pixel, parabola
        refinement), NaN where rejected.
    zncc : numpy.ndarray
        ZNCC of the winner (NaN where invalid).
    """
    vol = cost_volume(left, right, int(d_min), int(d_max), params.window)
    guide = np.asarray(left, np.float32) if params.p2_gamma else None
    S = aggregate(vol, params.P1, params.P2, guide=guide, p2_gamma=params.p2_gamma or 1.0)
    index, _, _, cbest = winner_take_all(S, vol)
    disp = (index + d_min).astype(np.float32)
    zncc = (1.0 - cbest).astype(np.float32)
    dr = _right_disparity(S, int(d_min))
    disp = _lr_check(disp, dr, np.float32(params.lr_max_diff))
    disp[~(zncc >= params.zncc_min)] = np.nan
    disp = remove_speckles(disp, params.speckle_diff, params.speckle_size)
    return disp, zncc


@nb.njit(nogil=True, cache=True)
def _fill_rows(d):
    ny, nx = d.shape
    out = d.copy()
    for i in range(ny):
        for x in range(nx):
            if np.isfinite(d[i, x]):
                continue
            a = np.nan
            for t in range(x - 1, -1, -1):
                if np.isfinite(d[i, t]):
                    a = d[i, t]
                    break
            b = np.nan
            for t in range(x + 1, nx):
                if np.isfinite(d[i, t]):
                    b = d[i, t]
                    break
            if np.isfinite(a) and np.isfinite(b):
                out[i, x] = min(a, b)
            elif np.isfinite(a):
                out[i, x] = a
            elif np.isfinite(b):
                out[i, x] = b
    return out


def fill_occlusions(disp: np.ndarray) -> np.ndarray:
    """Fill NaN disparities along rows with the smaller (background) of the
    nearest valid values left and right; rows without any valid value stay
    NaN. For evaluation against dense ground truth only."""
    return _fill_rows(np.ascontiguousarray(disp, np.float32))
