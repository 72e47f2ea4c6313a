"""Mismatch detection by point-to-line distance (P2L; Wan & Zhang 2017,
"Automatic detection of mismatches in satellite stereo image matching",
ISPRS J. Photogramm. Remote Sens. 130, 317-328), and plain RANSAC for
comparison.

For a match ``(p1, p2)``, ``p1`` is localised by camera 1 at several heights
across the scene's height range and projected by camera 2: the points trace
the "epipolar" curve of ``p1`` in image 2 (nearly a line over a short height
range). A correct match lies on it up to the relative pointing error of the
cameras, which is smooth over the image; a mismatch generally does not. The
signed distance of ``p2`` from the line is therefore fitted by a robust
affine trend in ``(row, col)`` of ``p1`` (the relative bias), and matches
whose residual from the trend exceeds ``k`` robust standard deviations
(1.4826 x MAD, at least ``floor_px``) are rejected (parameters
:class:`~tiledsm.orient.spec.P2LParams`, ``orient.tracks.p2l`` in a recipe).

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0)),
heights metres above the WGS84 ellipsoid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiledsm.geometry.rpc import RPC
from tiledsm.orient.spec import P2LParams

__all__ = ["P2LResult", "p2l_distances", "p2l_filter", "ransac_filter"]


@dataclass(frozen=True)
class P2LResult:
    """Outcome of :func:`p2l_filter`.

    Attributes
    ----------
    inlier : numpy.ndarray
        ``(n,)`` bool, matches kept.
    distance_px : numpy.ndarray
        ``(n,)`` signed point-to-line distances, pixels.
    residual_px : numpy.ndarray
        ``(n,)`` distances minus the fitted trend, pixels.
    threshold_px : float
    trend : numpy.ndarray
        ``(3,)`` coefficients of ``d = t0 + t1 * (row - row_mean) / S + t2 *
        (col - col_mean) / S`` with ``S`` the point spread.
    """

    inlier: np.ndarray
    distance_px: np.ndarray
    residual_px: np.ndarray
    threshold_px: float
    trend: np.ndarray


def p2l_distances(
    rpc1: RPC, rpc2: RPC, p1: np.ndarray, p2: np.ndarray, h_range: tuple[float, float], n_heights: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of each ``p2`` from the epipolar line of its ``p1``.

    The line is the total-least-squares line through the projections in
    image 2 of ``p1`` localised at ``n_heights`` heights spread over
    ``h_range``; the sign is that of the line normal obtained by rotating
    the mean line direction of all matches by +90 degrees (so a common
    relative shift gives distances of one sign).

    Returns
    -------
    distance : numpy.ndarray
        ``(n,)`` pixels.
    direction : numpy.ndarray
        ``(n, 2)`` unit direction of each line (towards increasing height).
    """
    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    hs = np.linspace(float(h_range[0]), float(h_range[1]), max(2, int(n_heights)))
    lon, lat = rpc1.localize(p1[:, 0:1], p1[:, 1:2], hs[None, :])
    q = np.stack(rpc2.project(lon, lat, np.broadcast_to(hs[None, :], lon.shape)), -1)  # (n, m, 2)
    qm = q.mean(axis=1)
    u = q[:, -1] - q[:, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if q.shape[1] > 2:  # refine the direction by TLS (a curved locus)
        c = q - qm[:, None]
        cov = np.einsum("nmi,nmj->nij", c, c)
        _, vec = np.linalg.eigh(cov)
        v = vec[:, :, -1]
        v *= np.sign(np.einsum("ij,ij->i", v, u))[:, None]
        u = v
    mean_u = u.mean(axis=0)
    mean_u /= np.linalg.norm(mean_u)
    nrm = np.stack([-u[:, 1], u[:, 0]], -1)
    nrm *= np.sign(np.einsum("ij,j->i", nrm, np.array([-mean_u[1], mean_u[0]])))[:, None]
    return np.einsum("ij,ij->i", nrm, p2 - qm), u


def _robust_trend(d: np.ndarray, p1: np.ndarray, k: float, floor: float, iterations: int):
    centre = np.median(p1, axis=0)
    spread = max(float(np.ptp(p1)) if p1.size else 1.0, 1.0)
    a = np.column_stack([np.ones(len(d)), (p1 - centre) / spread])
    keep = np.ones(len(d), bool)
    coef = np.zeros(3)
    thr = floor
    for _ in range(iterations):
        if keep.sum() < 3:
            break
        coef = np.linalg.lstsq(a[keep], d[keep], rcond=None)[0]
        res = d - a @ coef
        sigma = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep]))))
        thr = max(floor, k * sigma)
        new = np.abs(res) <= thr
        if np.array_equal(new, keep):
            break
        keep = new
    return d - a @ coef, thr, coef


def p2l_filter(
    rpc1: RPC, rpc2: RPC, p1: np.ndarray, p2: np.ndarray, h_range: tuple[float, float],
    params: P2LParams = P2LParams(),
) -> P2LResult:
    """Reject mismatches by their point-to-line distance (module docstring).

    Parameters
    ----------
    rpc1, rpc2 : RPC
        The cameras as they are (biased or not: the relative bias is the
        fitted trend).
    p1, p2 : numpy.ndarray
        ``(n, 2)`` matched ``(row, col)``, GDAL convention.
    h_range : (float, float)
        Scene heights, metres (ellipsoidal).
    params : P2LParams
    """
    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    if len(p1) == 0:
        z = np.zeros(0)
        return P2LResult(np.zeros(0, bool), z, z, params.floor_px, np.zeros(3))
    d, _ = p2l_distances(rpc1, rpc2, p1, p2, h_range, params.n_heights)
    res, thr, coef = _robust_trend(d, p1, params.k, params.floor_px, params.iterations)
    return P2LResult(np.abs(res) <= thr, d, res, float(thr), coef)


def ransac_filter(p1: np.ndarray, p2: np.ndarray, threshold_px: float = 1.0, confidence: float = 0.999,
                  max_iters: int = 5000, seed: int = 0) -> np.ndarray:
    """Plain RANSAC on a fundamental matrix (OpenCV ``FM_RANSAC``): the
    inlier mask of the matches, ``threshold_px`` the distance to the
    epipolar line. The baseline P2L is compared with."""
    import cv2

    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    if len(p1) < 8:
        return np.zeros(len(p1), bool)
    cv2.setRNGSeed(seed)
    _, inl = cv2.findFundamentalMat(p1[:, ::-1].astype(np.float64), p2[:, ::-1].astype(np.float64),
                                    cv2.FM_RANSAC, threshold_px, confidence, max_iters)
    return np.zeros(len(p1), bool) if inl is None else inl.ravel().astype(bool)
