"""Space intersection of image points seen by two RPC cameras.

Conventions: pixel coordinates ``(row, col)`` in GDAL convention (see
:mod:`tiledsm.geometry.rpc`); lon/lat degrees, heights metres above the
WGS84 ellipsoid.
"""

from __future__ import annotations

import numpy as np

from tiledsm.geometry import RPC

__all__ = ["triangulate"]


def _residuals(rpc1, rpc2, p1, p2, lon, lat, h):
    r1, c1 = rpc1.project(lon, lat, h)
    r2, c2 = rpc2.project(lon, lat, h)
    return np.stack([r1 - p1[:, 0], c1 - p1[:, 1], r2 - p2[:, 0], c2 - p2[:, 1]], axis=-1)


def triangulate(
    rpc1: RPC, rpc2: RPC, p1: np.ndarray, p2: np.ndarray, h0: float | None = None, n_iter: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares intersection of corresponding points (vectorised).

    Minimises the four reprojection residuals (row/col in both images) over
    ``(lon, lat, h)`` by Gauss-Newton with a numerical Jacobian, starting
    from ``rpc1.localize(p1, h0)``.

    Parameters
    ----------
    rpc1, rpc2 : RPC
    p1, p2 : numpy.ndarray
        ``(n, 2)`` pixel coordinates ``(row, col)``, GDAL convention.
    h0 : float, optional
        Starting height (default: ``rpc1.height_off``).
    n_iter : int
        Gauss-Newton iterations.

    Returns
    -------
    lon, lat, h : numpy.ndarray
        ``(n,)`` degrees, degrees, metres.
    residual_px : numpy.ndarray
        ``(n,)`` RMS reprojection residual over the four coordinates, pixels.
    """
    p1 = np.atleast_2d(np.asarray(p1, float))
    p2 = np.atleast_2d(np.asarray(p2, float))
    if p1.shape != p2.shape or p1.shape[-1] != 2:
        raise ValueError(f"triangulate: p1 and p2 must both be (n, 2), got {p1.shape} and {p2.shape}")
    h = np.full(len(p1), rpc1.height_off if h0 is None else float(h0))
    lon, lat = rpc1.localize(p1[:, 0], p1[:, 1], h)
    steps = np.array([1e-6, 1e-6, 0.1])
    for _ in range(n_iter):
        r = _residuals(rpc1, rpc2, p1, p2, lon, lat, h)
        J = np.empty(r.shape + (3,))
        J[..., 0] = (_residuals(rpc1, rpc2, p1, p2, lon + steps[0], lat, h) - r) / steps[0]
        J[..., 1] = (_residuals(rpc1, rpc2, p1, p2, lon, lat + steps[1], h) - r) / steps[1]
        J[..., 2] = (_residuals(rpc1, rpc2, p1, p2, lon, lat, h + steps[2]) - r) / steps[2]
        JtJ = np.einsum("nki,nkj->nij", J, J)
        Jtr = np.einsum("nki,nk->ni", J, r)
        # column scaling for conditioning
        sc = np.sqrt(np.maximum(np.einsum("nii->ni", JtJ), 1e-30))
        A = JtJ / (sc[:, :, None] * sc[:, None, :])
        delta = -np.linalg.solve(A + 1e-12 * np.eye(3), (Jtr / sc)[..., None])[..., 0] / sc
        lon, lat, h = lon + delta[:, 0], lat + delta[:, 1], h + delta[:, 2]
        if np.all(np.abs(delta[:, 2]) < 1e-4):
            break
    r = _residuals(rpc1, rpc2, p1, p2, lon, lat, h)
    return lon, lat, h, np.sqrt(np.mean(r**2, axis=-1))
