"""Tie points between two images, the scene height range they imply, and
the relative pointing correction of the second camera.

Conventions: pixel coordinates are ``(row, col)`` in GDAL convention (the
centre of array element ``[i, j]`` is at ``(i + 0.5, j + 0.5)``); heights
are metres above the WGS84 ellipsoid.
"""

from __future__ import annotations

import cv2
import numpy as np

from tiledsm.errors import MatchingError
from tiledsm.geometry import RPC
from tiledsm.match.triangulate import triangulate

__all__ = ["to_uint8", "match_tiepoints", "supported", "height_range_from_tiepoints", "relative_correction"]


def to_uint8(img: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.0)) -> tuple[np.ndarray, np.ndarray]:
    """Stretch an image to 8 bits between two percentiles of its valid
    values; returns the 8-bit image (nodata -> 0) and the validity mask."""
    a = np.asarray(img, np.float32)
    ok = np.isfinite(a)
    if not ok.any():
        return np.zeros(a.shape, np.uint8), ok
    lo, hi = np.percentile(a[ok], percentiles)
    hi = hi if hi > lo else lo + 1.0
    out = np.clip((np.where(ok, a, lo) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    return out, ok


def match_tiepoints(
    img1: np.ndarray,
    img2: np.ndarray,
    ratio: float = 0.8,
    ransac_px: float | None = None,
    max_size: int = 2000,
    n_features: int = 4000,
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT tie points filtered by Lowe's ratio test (and optionally a
    RANSAC fundamental matrix).

    Parameters
    ----------
    img1, img2 : numpy.ndarray
        2-D images (any dtype; NaN = nodata), stretched to 8 bits.
    ratio : float
        Lowe's ratio test threshold.
    ransac_px : float, optional
        When given, also keep only the inliers of a RANSAC fundamental
        matrix at this distance to the epipolar line (pixels of the full
        images). Off by default: a fundamental matrix only approximates
        pushbroom (RPC) geometry, and points far above the ground its fit
        is carried by lie off it (the roof of a 65 m tower on a 384 px
        synthetic pair: 1.2 px from one draw's matrix, more from others,
        so whether a scene's only roof points survived depended on
        RANSAC's draw). The callers filter with the RPCs instead
        (triangulation residual, neighbour support, robust medians).
    max_size : int
        Images larger than this (pixels, longest side) are area-downsampled
        for detection; coordinates are returned in full-image pixels.
    n_features : int
        Maximum SIFT features per image.

    Returns
    -------
    p1, p2 : numpy.ndarray
        ``(n, 2)`` float64 ``(row, col)`` GDAL coordinates of matching
        points in ``img1`` and ``img2`` (``n`` may be 0).
    """
    pts = []
    for img in (img1, img2):
        a = np.asarray(img, np.float32)
        f = max(1, int(np.ceil(max(a.shape) / max_size)))
        if f > 1:
            from tiledsm.match.pyramid import downsample

            a = downsample(a, f)
        u8, ok = to_uint8(a)
        mask = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8))
        sift = cv2.SIFT_create(nfeatures=n_features)
        kp, desc = sift.detectAndCompute(u8, mask)
        xy = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
        # OpenCV: pixel centres at integers -> GDAL corner convention, full image
        pts.append(((xy[:, ::-1] + 0.5) * f, desc))
    (q1, d1), (q2, d2) = pts
    empty = np.zeros((0, 2))
    if d1 is None or d2 is None or len(q1) < 8 or len(q2) < 8:
        return empty, empty
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < 8:
        return empty, empty
    i1 = np.array([m.queryIdx for m in good])
    i2 = np.array([m.trainIdx for m in good])
    p1, p2 = q1[i1], q2[i2]
    if ransac_px is None:
        return p1, p2
    _, inl = cv2.findFundamentalMat(
        p1[:, ::-1].astype(np.float32), p2[:, ::-1].astype(np.float32), cv2.FM_RANSAC, ransac_px, 0.999, 5000
    )
    if inl is None:
        return empty, empty
    keep = inl.ravel().astype(bool)
    return p1[keep], p2[keep]


def supported(xy: np.ndarray, h: np.ndarray, radius: float, tol: float, min_support: int) -> np.ndarray:
    """Points whose height is confirmed by neighbours.

    A point is supported when at least ``min_support`` other points lie
    within ``radius`` of it (ground metres) with a height within ``tol``
    metres of its own. A roof, a peak or a cliff top carries several
    consistent tie points; a mismatch along the epipolar line is a lone
    height.

    Parameters
    ----------
    xy : numpy.ndarray
        ``(n, 2)`` ground positions, metres (any local metric frame).
    h : numpy.ndarray
        ``(n,)`` heights, metres.
    radius, tol : float
        Neighbourhood radius and height tolerance, metres.
    min_support : int
        Consistent neighbours needed.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` bool.
    """
    from scipy.spatial import cKDTree

    if len(h) == 0:
        return np.zeros(0, bool)
    near = cKDTree(xy).query_ball_point(xy, radius)
    count = np.array([np.count_nonzero(np.abs(h[n] - h[i]) <= tol) - 1 for i, n in enumerate(near)])
    return count >= min_support


def height_range_from_tiepoints(
    rpc1: RPC,
    rpc2: RPC,
    p1: np.ndarray,
    p2: np.ndarray,
    margin: float = 10.0,
    max_residual: float | None = None,
    support_radius: float = 50.0,
    support_tol: float = 5.0,
    min_support: int = 2,
) -> tuple[float, float]:
    """Scene height range from triangulated tie points: the lowest and the
    highest *supported* point, widened by ``margin`` metres on both sides
    and kept inside the RPCs' height validity range.

    Extremes, not percentiles: a tower or a peak is a handful of tie
    points (a 16 m tower on 0.15 km^2 is 5 of 2000), which any percentile
    drops, and a search range that stops below a roof cannot find it. Lone
    mismatches, which percentiles were there to drop, are removed by
    :func:`supported` instead. Points whose reprojection residual exceeds
    ``max_residual`` pixels (default: ``max(1, 3 x median residual)``) are
    dropped first.

    Raises
    ------
    MatchingError
        With fewer than 5 usable points.
    """
    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    if len(p1) < 5:
        raise MatchingError(f"height range: only {len(p1)} tie points (need >= 5)")
    lon, lat, h, res = triangulate(rpc1, rpc2, p1, p2)
    ok = np.isfinite(h) & np.isfinite(res)
    thr = max_residual if max_residual is not None else max(1.0, 3.0 * float(np.median(res[ok])))
    ok &= res <= thr
    if ok.sum() < 5:
        raise MatchingError(f"height range: only {int(ok.sum())} tie points with residual <= {thr:.2f} px")
    lon, lat, h = lon[ok], lat[ok], h[ok]
    # a local equirectangular frame is metric enough for a 50 m neighbourhood
    xy = np.column_stack([(lon - lon.mean()) * 111_320.0 * np.cos(np.radians(lat.mean())), (lat - lat.mean()) * 110_540.0])
    keep = supported(xy, h, support_radius, support_tol, min_support)
    if keep.sum() < 5:
        raise MatchingError(
            f"height range: only {int(keep.sum())} tie points confirmed by neighbours "
            f"({min_support} within {support_radius:g} m and {support_tol:g} m in height)"
        )
    lo, hi = float(h[keep].min()) - margin, float(h[keep].max()) + margin
    valid = [(r.height_off - abs(r.height_scale), r.height_off + abs(r.height_scale)) for r in (rpc1, rpc2)]
    lo, hi = max(lo, *(v[0] for v in valid)), min(hi, *(v[1] for v in valid))
    if hi <= lo:
        raise MatchingError(f"height range: tie points at {h[keep].min():.1f}..{h[keep].max():.1f} m lie outside "
                            "the RPCs' height validity range")
    return lo, hi


def relative_correction(
    rpc1: RPC, rpc2: RPC, p1: np.ndarray, p2: np.ndarray, details: dict | None = None
) -> tuple[float, float]:
    """Image translation of view 2 that removes the relative pointing error.

    For each tie point the epipolar line of ``p1`` in image 2 is traced
    through two heights; the signed distance of ``p2`` from it is the
    pointing error across the epipolar direction (the component along it is
    indistinguishable from a height change). The correction is the median
    distance along the mean epipolar normal.

    Parameters
    ----------
    rpc1, rpc2 : RPC
    p1, p2 : numpy.ndarray
        ``(n, 2)`` ``(row, col)`` GDAL coordinates of tie points.
    details : dict, optional
        Filled with ``residual_before_px`` / ``residual_after_px`` (median
        absolute epipolar distance) and ``n``.

    Returns
    -------
    drow, dcol : float
        Pixels to add to rows/columns projected by ``rpc2`` (i.e. to its
        ``line_off`` / ``samp_off``).
    """
    p1 = np.asarray(p1, float).reshape(-1, 2)
    p2 = np.asarray(p2, float).reshape(-1, 2)
    if len(p1) < 3:
        raise MatchingError(f"relative correction: only {len(p1)} tie points (need >= 3)")
    _, _, h, _ = triangulate(rpc1, rpc2, p1, p2)
    hm = float(np.median(h[np.isfinite(h)])) if np.isfinite(h).any() else rpc1.height_off
    ha, hb = hm - 0.5 * rpc1.height_scale * 0.1, hm + 0.5 * rpc1.height_scale * 0.1
    lon_a, lat_a = rpc1.localize(p1[:, 0], p1[:, 1], ha)
    lon_b, lat_b = rpc1.localize(p1[:, 0], p1[:, 1], hb)
    qa = np.stack(rpc2.project(lon_a, lat_a, ha), -1)
    qb = np.stack(rpc2.project(lon_b, lat_b, hb), -1)
    u = qb - qa
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    n = np.stack([-u[:, 1], u[:, 0]], -1)
    e = np.einsum("ij,ij->i", n, p2 - qa)
    nm = n.mean(axis=0)
    nm /= np.linalg.norm(nm)
    t = float(np.median(e)) * nm
    if details is not None:
        after = np.einsum("ij,ij->i", n, p2 - qa - t)
        details.update(
            n=int(len(p1)),
            residual_before_px=float(np.median(np.abs(e))),
            residual_after_px=float(np.median(np.abs(after))),
        )
    return float(t[0]), float(t[1])
