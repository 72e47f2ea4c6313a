"""Terrain attributes of a DSM block: metric pixel size, slope, aspect, hillshade.

Conventions
-----------
- Arrays are ``[row, col]``; a north-up grid has rows going south.
- ``step_x`` is the signed ground distance, in metres **east**, from one
  column to the next; ``step_y`` the signed distance in metres **north** from
  one row to the next (negative for a north-up grid). Both may be arrays of
  shape ``(rows, 1)`` (geographic CRS: the metric size of a degree varies
  with latitude).
- Slope: degrees from horizontal. Aspect: direction of steepest *descent*,
  radians clockwise from north in ``[0, 2*pi)``.
- Gradients use Horn's (1981) 3x3 weights, as ``gdaldem slope``; cells whose
  3x3 neighbourhood holds a NaN (or lies outside the block) are NaN.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["metric_steps", "horn_gradient", "slope_aspect", "slope_percent", "hillshade"]

_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3


def metric_steps(crs, transform, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed metres east per column step and north per row step.

    Parameters
    ----------
    crs : rasterio.crs.CRS
        Grid CRS (projected or geographic).
    transform : affine.Affine
        North-up or south-up grid transform (no rotation).
    y : ndarray
        CRS y coordinate (latitude in degrees for a geographic CRS) of the
        rows, shape ``(rows,)``.

    Returns
    -------
    step_x, step_y : ndarray, shape ``(rows, 1)``
        For a projected CRS the transform terms times the CRS linear unit
        (map scale distortion is ignored); for a geographic CRS the
        ellipsoidal (WGS84) metric length of ``transform.a`` degrees of
        longitude and ``transform.e`` degrees of latitude at each row.
    """
    y = np.asarray(y, dtype=np.float64).reshape(-1, 1)
    if crs.is_geographic:
        phi = np.deg2rad(y)
        w = np.sqrt(1.0 - _WGS84_E2 * np.sin(phi) ** 2)
        m_per_deg_lon = np.deg2rad(1.0) * _WGS84_A * np.cos(phi) / w
        m_per_deg_lat = np.deg2rad(1.0) * _WGS84_A * (1.0 - _WGS84_E2) / w**3
        return transform.a * m_per_deg_lon, transform.e * m_per_deg_lat
    unit = crs.linear_units_factor[1] if crs.linear_units_factor else 1.0
    ones = np.ones_like(y)
    return transform.a * unit * ones, transform.e * unit * ones


def horn_gradient(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horn 3x3 derivatives ``dz/dcol`` and ``dz/drow`` (height units per pixel).

    Border cells (and cells next to a NaN) are NaN.
    """
    z = np.asarray(z, dtype=np.float64)
    p = np.pad(z, 1, constant_values=np.nan)
    a, b, c = p[:-2, :-2], p[:-2, 1:-1], p[:-2, 2:]
    d, f = p[1:-1, :-2], p[1:-1, 2:]
    g, h, i = p[2:, :-2], p[2:, 1:-1], p[2:, 2:]
    dcol = ((c + 2 * f + i) - (a + 2 * d + g)) / 8.0
    drow = ((g + 2 * h + i) - (a + 2 * b + c)) / 8.0
    return dcol, drow


def slope_aspect(z: np.ndarray, step_x, step_y) -> tuple[np.ndarray, np.ndarray]:
    """Slope (degrees) and aspect (radians, downslope, clockwise from north).

    Parameters
    ----------
    z : ndarray
        Heights (metres), ``[row, col]``.
    step_x, step_y : float or ndarray
        Signed metres east per column and north per row (see module notes).
    """
    dcol, drow = horn_gradient(z)
    gx = dcol / step_x  # dz / d(east)
    gy = drow / step_y  # dz / d(north)
    slope = np.rad2deg(np.arctan(np.hypot(gx, gy)))
    aspect = np.mod(np.arctan2(-gx, -gy), 2 * np.pi)
    return slope, aspect


def slope_percent(z: np.ndarray, step_x, step_y) -> np.ndarray:
    """Slope as a percentage (100 x rise / run), as demcompare's slope classes.

    ``100 * |(dcol / step_x, drow / step_y)|`` with Horn's derivatives
    (:func:`horn_gradient`), in one compiled pass when the steps are scalars
    or per-row ``(rows, 1)`` arrays, else with numpy broadcasting. The
    compiled pass takes the norm as ``sqrt(gx**2 + gy**2)`` (libm's ``hypot``
    costs 4x the rest): within 3e-16 relative of ``np.hypot``, and equal to
    it once rounded to float32 on the 5 M cells checked.
    """
    z = np.asarray(z)
    rows = z.shape[0]
    sx, sy = np.asarray(step_x, dtype=np.float64), np.asarray(step_y, dtype=np.float64)
    if z.ndim == 2 and all(s.size == 1 or s.shape == (rows, 1) for s in (sx, sy)):
        out = np.empty(z.shape, dtype=np.float64)
        _slope_percent(z, np.broadcast_to(sx.reshape(-1), (rows,)), np.broadcast_to(sy.reshape(-1), (rows,)), out)
        return out
    dcol, drow = horn_gradient(z)
    return 100.0 * np.hypot(dcol / step_x, drow / step_y)


@numba.njit(nogil=True, cache=True)
def _slope_percent(z, sx, sy, out):  # pragma: no cover - compiled
    H, W = z.shape
    for i in range(H):
        for j in range(W):
            if i == 0 or j == 0 or i == H - 1 or j == W - 1:
                out[i, j] = np.nan
                continue
            a, b, c = np.float64(z[i - 1, j - 1]), np.float64(z[i - 1, j]), np.float64(z[i - 1, j + 1])
            d, f = np.float64(z[i, j - 1]), np.float64(z[i, j + 1])
            g, h, k = np.float64(z[i + 1, j - 1]), np.float64(z[i + 1, j]), np.float64(z[i + 1, j + 1])
            dcol = ((c + 2.0 * f + k) - (a + 2.0 * d + g)) / 8.0
            drow = ((g + 2.0 * h + k) - (a + 2.0 * b + c)) / 8.0
            gx, gy = dcol / sx[i], drow / sy[i]
            out[i, j] = 100.0 * np.sqrt(gx * gx + gy * gy)


def hillshade(z: np.ndarray, step_x, step_y, azimuth_deg: float = 315.0, altitude_deg: float = 45.0) -> np.ndarray:
    """Lambertian hillshade in ``[0, 1]`` (NaN where the slope is undefined)."""
    dcol, drow = horn_gradient(z)
    gx = dcol / step_x
    gy = drow / step_y
    az = np.deg2rad(azimuth_deg)
    alt = np.deg2rad(altitude_deg)
    # unit normal of the surface (east, north, up) dotted with the sun direction
    norm = np.sqrt(1.0 + gx**2 + gy**2)
    sun = (np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt))
    shade = (-gx * sun[0] - gy * sun[1] + sun[2]) / norm
    return np.clip(shade, 0.0, 1.0)
