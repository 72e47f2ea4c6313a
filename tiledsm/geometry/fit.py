"""Terrain-independent RPC fitting: regenerate a third-order RPC from any
projection sampled over a virtual 3-D ground grid.

The rational function ``l = P(t) / Q(t)`` (``t`` the 20 RPC00B monomials of
normalised lon/lat/height, ``Q[0] = 1``) is linearised as
``P(t) - l * (Q(t) - 1) = l`` and solved by Tikhonov-regularised linear least
squares, iterated with weights ``1 / Q`` from the previous solution so that
the minimised quantity tends to the true image residual ``P/Q - l``
(Tao & Hu 2001, "A comprehensive study of the rational function model for
photogrammetric processing", PE&RS 67(12), 1347-1357). The fit is judged on
*held-out* points: the centres of the fitting grid's cells, which the
solver never sees.

Conventions
-----------
``project_fn(lon, lat, h) -> (row, col)`` uses GDAL's pixel convention (the
top-left image corner at (0, 0); pixel ``[i, j]`` centred at
``(i + .5, j + .5)``), lon/lat in WGS84 degrees, ``h`` in metres above the
WGS84 ellipsoid, and must broadcast over numpy arrays. It may return NaN
for points it cannot project: those are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from tiledsm.errors import RPCError
from tiledsm.geometry.rpc import RPC, rpc_terms

__all__ = ["FitReport", "fit_rpc", "fit_rpc_report", "with_affine"]

ProjectFn = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class FitReport:
    """Accuracy of a fitted RPC, in pixels.

    Attributes
    ----------
    check_rmse_px, check_max_px : float
        RMS and maximum of the 2-D image error ``hypot(drow, dcol)`` on the
        held-out check points (cell centres of the fitting grid).
    fit_max_px : float
        Maximum 2-D error on the fitting points themselves.
    n_fit, n_check : int
        Number of (finite) fitting and check points.
    iterations : int
        Reweighting iterations used (line and sample: the larger).
    """

    check_rmse_px: float
    check_max_px: float
    fit_max_px: float
    n_fit: int
    n_check: int
    iterations: int


def _grid(lon_range, lat_range, h_range, n_xy: int, n_h: int, held_out: bool):
    """Ground grid nodes (``held_out=False``) or cell centres (``True``)."""

    def axis(r, n):
        a, b = float(r[0]), float(r[1])
        nodes = np.linspace(a, b, n)
        return 0.5 * (nodes[1:] + nodes[:-1]) if held_out else nodes

    lon = axis(lon_range, n_xy)
    lat = axis(lat_range, n_xy)
    h = axis(h_range, n_h) if n_h > 1 else np.array([0.5 * (h_range[0] + h_range[1])])
    return [a.ravel() for a in np.meshgrid(lon, lat, h, indexing="ij")]


def _fit_rational(t: np.ndarray, v: np.ndarray, lam: float, n_iter: int, tol: float):
    """Fit ``v ≈ (num · t) / (den · t)`` with ``den[0] = 1``.

    ``t`` is (20, n), ``v`` (n,). Returns (num, den, iterations). Each pass
    solves the weighted, Tikhonov-regularised linearised system with a
    stable least-squares solver (augmented matrix, no normal equations);
    the best pass (smallest true max residual) is kept.
    """
    tt = t.T  # (n, 20)
    a = np.hstack([tt, -v[:, None] * tt[:, 1:]])  # (n, 39)
    reg = np.sqrt(lam) * np.eye(a.shape[1])
    zeros = np.zeros(a.shape[1])
    w = np.ones_like(v)
    best = None
    it = 0
    for it in range(1, n_iter + 1):
        sol, *_ = np.linalg.lstsq(np.vstack([a * w[:, None], reg]), np.concatenate([v * w, zeros]), rcond=None)
        num, den = sol[:20], np.concatenate([[1.0], sol[20:]])
        q = den @ t
        err = np.max(np.abs(num @ t / q - v))
        if best is None or err < best[0]:
            prev = best[0] if best is not None else np.inf
            best = (err, num, den)
            if prev - err <= tol * max(err, 1e-300) and it > 1:
                break
        else:
            break
        if np.any(q == 0):
            break
        w = 1.0 / q
    return best[1], best[2], it


def fit_rpc_report(
    project_fn: ProjectFn,
    lon_range: tuple[float, float],
    lat_range: tuple[float, float],
    h_range: tuple[float, float],
    image_shape: tuple[int, int] | None = None,
    *,
    image_window: tuple[float, float, float, float] | None = None,
    n_xy: int = 21,
    n_h: int = 9,
    regularisation: float = 1e-12,
    n_iter: int = 10,
    source: str = "fit_rpc",
) -> tuple[RPC, FitReport]:
    """Fit an RPC to ``project_fn`` and report its held-out accuracy.

    Same parameters as :func:`fit_rpc`; ``image_window = (row0, row1, col0,
    col1)`` (GDAL convention) may replace ``image_shape`` to set the image
    normalisation box of a window not starting at (0, 0).
    """
    if image_window is None:
        if image_shape is None:
            raise ValueError("fit_rpc: give image_shape or image_window")
        image_window = (0.0, float(image_shape[0]), 0.0, float(image_shape[1]))
    r0, r1, c0, c1 = (float(v) for v in image_window)
    if not (r1 > r0 and c1 > c0):
        raise ValueError(f"fit_rpc: empty image window {image_window}")
    for name, r in (("lon_range", lon_range), ("lat_range", lat_range)):
        if not (np.all(np.isfinite(r)) and r[1] > r[0]):
            raise ValueError(f"fit_rpc: {name} must be finite and increasing, got {r}")
    if not (np.all(np.isfinite(h_range)) and h_range[1] >= h_range[0]):
        raise ValueError(f"fit_rpc: h_range must be finite and non-decreasing, got {h_range}")
    if n_xy < 4 or n_h < 1:
        raise ValueError("fit_rpc: need n_xy >= 4 and n_h >= 1")

    # Normalisation (RPC standard: line_off/samp_off in the first-pixel-centre convention).
    lon_off, lon_scale = 0.5 * (lon_range[0] + lon_range[1]), 0.5 * (lon_range[1] - lon_range[0])
    lat_off, lat_scale = 0.5 * (lat_range[0] + lat_range[1]), 0.5 * (lat_range[1] - lat_range[0])
    h_off = 0.5 * (h_range[0] + h_range[1])
    h_scale = max(0.5 * (h_range[1] - h_range[0]), 1.0)
    line_scale, samp_scale = 0.5 * (r1 - r0), 0.5 * (c1 - c0)
    line_off, samp_off = 0.5 * (r0 + r1) - 0.5, 0.5 * (c0 + c1) - 0.5

    def sample(held_out: bool):
        lon, lat, h = _grid(lon_range, lat_range, h_range, n_xy, n_h if n_h > 1 else 1, held_out)
        row, col = (np.asarray(a, float) for a in project_fn(lon, lat, h))
        row, col = np.broadcast_to(row, lon.shape), np.broadcast_to(col, lon.shape)
        ok = np.isfinite(row) & np.isfinite(col)
        return lon[ok], lat[ok], h[ok], row[ok], col[ok]

    lon, lat, h, row, col = sample(False)
    if lon.size < 39 * 2:
        raise RPCError(f"fit_rpc ({source}): only {lon.size} finite projections on the fitting grid")
    t = rpc_terms((lon - lon_off) / lon_scale, (lat - lat_off) / lat_scale, (h - h_off) / h_scale)
    ln = (row - 0.5 - line_off) / line_scale
    sn = (col - 0.5 - samp_off) / samp_scale
    tol = 1e-3
    line_num, line_den, it_l = _fit_rational(t, ln, regularisation, n_iter, tol)
    samp_num, samp_den, it_s = _fit_rational(t, sn, regularisation, n_iter, tol)
    rpc = RPC(
        line_off=line_off, samp_off=samp_off, lat_off=lat_off, lon_off=lon_off, height_off=h_off,
        line_scale=line_scale, samp_scale=samp_scale, lat_scale=lat_scale, lon_scale=lon_scale,
        height_scale=h_scale, line_num=line_num, line_den=line_den, samp_num=samp_num,
        samp_den=samp_den, source=source,
    )
    fr, fc = rpc.project(lon, lat, h)
    fit_err = np.hypot(fr - row, fc - col)
    clon, clat, ch, crow, ccol = sample(True) if n_h > 1 else sample(True)
    pr, pc = rpc.project(clon, clat, ch)
    chk = np.hypot(pr - crow, pc - ccol)
    report = FitReport(
        check_rmse_px=float(np.sqrt(np.mean(chk**2))) if chk.size else float("nan"),
        check_max_px=float(np.max(chk)) if chk.size else float("nan"),
        fit_max_px=float(np.max(fit_err)),
        n_fit=int(lon.size),
        n_check=int(clon.size),
        iterations=max(it_l, it_s),
    )
    return rpc, report


def fit_rpc(
    project_fn: ProjectFn,
    lon_range: tuple[float, float],
    lat_range: tuple[float, float],
    h_range: tuple[float, float],
    image_shape: tuple[int, int] | None = None,
    *,
    image_window: tuple[float, float, float, float] | None = None,
    n_xy: int = 21,
    n_h: int = 9,
    regularisation: float = 1e-12,
    n_iter: int = 10,
    max_error: float | None = None,
    source: str = "fit_rpc",
) -> RPC:
    """Regenerate a third-order RPC (RPC00B) from any projection.

    Parameters
    ----------
    project_fn : callable
        ``project_fn(lon, lat, h) -> (row, col)``: lon/lat WGS84 degrees,
        ``h`` metres above the ellipsoid, row/col in GDAL's pixel convention
        (top-left image corner at (0, 0)). Vectorised; NaN = not projectable.
    lon_range, lat_range : (float, float)
        Ground extent of the virtual grid, degrees (min, max).
    h_range : (float, float)
        Height extent, metres above the ellipsoid (min, max). Use a range
        slightly wider than the terrain's.
    image_shape : (int, int)
        ``(rows, cols)`` of the image; sets the image normalisation
        (offsets at the image centre, scales half the size).
    image_window : (row0, row1, col0, col1), optional
        Instead of ``image_shape``: the image box for normalisation.
    n_xy, n_h : int
        Virtual grid nodes per horizontal axis and in height (the fit uses
        ``n_xy * n_xy * n_h`` points; at least 39 per coordinate are
        needed). The ``(n_xy-1)**2 * (n_h-1)`` cell centres are held out.
    regularisation : float
        Tikhonov weight λ on the coefficients of the normalised model
        (targets and monomials lie in [-1, 1]). Keeps the denominator
        bounded when terms are nearly collinear (small regions, flat height
        range); 1e-12 leaves exact models exact.
    n_iter : int
        Maximum reweighting passes (weights ``1/Q`` of the previous pass).
    max_error : float, optional
        When given, raise :class:`~tiledsm.errors.RPCError` if the held-out
        maximum error exceeds it (pixels).
    source : str
        Stored in ``RPC.source``.

    Returns
    -------
    RPC
        Normalised over the given ground box and image box. Use
        :func:`fit_rpc_report` to get the accuracy figures too.
    """
    rpc, rep = fit_rpc_report(
        project_fn, lon_range, lat_range, h_range, image_shape, image_window=image_window,
        n_xy=n_xy, n_h=n_h, regularisation=regularisation, n_iter=n_iter, source=source,
    )
    if max_error is not None and not rep.check_max_px <= max_error:
        raise RPCError(
            f"fit_rpc ({source}): held-out error {rep.check_max_px:.4g} px exceeds max_error={max_error} px"
        )
    return rpc


def with_affine(
    rpc: RPC,
    a,
    b,
    *,
    image_shape: tuple[int, int] | None = None,
    h_range: tuple[float, float] | None = None,
    max_error: float = 0.01,
) -> RPC:
    """Fold an image-space affine bias correction into a new RPC.

    The bias-compensated RPC model (Grodecki & Dial 2003, PE&RS 69(1)
    59-68; Fraser & Hanley 2003, PE&RS 69(1) 53-57), with ``(l, s)`` the
    *measured* line/sample of a ground point in GDAL's pixel convention
    (``row``/``col`` as returned by :meth:`RPC.project`) and ``(r, c)``
    ``rpc``'s projection of it::

        l + A0 + A1 * l + A2 * s = r
        s + B0 + B1 * l + B2 * s = c

    The returned RPC projects ground points to the measured ``(l, s)``
    (the 2x2 system solved for them): it is ``rpc`` with its bias
    removed and needs no extra terms.

    When ``A2 == B1 == 0`` (shift + per-axis scale) the result is exact
    (only offsets and scales change). Otherwise the corrected projection
    is refitted with :func:`fit_rpc` over the ground
    seen by the image (corners localised at ``h_range``) and checked on
    held-out points: an :class:`~tiledsm.errors.RPCError` is raised if
    the fit is worse than ``max_error`` pixels.

    Parameters
    ----------
    a, b : sequence of 3 floats
        ``(A0, A1, A2)`` and ``(B0, B1, B2)``; A0/B0 in pixels, the
        others dimensionless.
    image_shape : (rows, cols), optional
        Image extent (measured pixel frame) for the refit; default: this
        RPC's :meth:`image_window` mapped to the measured frame.
    h_range : (float, float), optional
        Heights (m, ellipsoidal) for the refit; default
        ``height_off ± height_scale``.
    max_error : float
        Held-out tolerance of the refit, pixels.
    """
    a0, a1, a2 = (float(v) for v in a)
    b0, b1, b2 = (float(v) for v in b)
    det = (1.0 + a1) * (1.0 + b2) - a2 * b1
    if not (np.isfinite(det) and abs(det) > 1e-6):
        raise RPCError(f"with_affine: singular correction (A={a}, B={b})")
    src = f"{rpc.source} + affine" if rpc.source else "affine-corrected"
    if a2 == 0.0 and b1 == 0.0:
        ka, kb = 1.0 + a1, 1.0 + b2
        return rpc.replace(
            line_off=(rpc.line_off + 0.5 - a0) / ka - 0.5, line_scale=rpc.line_scale / ka,
            samp_off=(rpc.samp_off + 0.5 - b0) / kb - 0.5, samp_scale=rpc.samp_scale / kb,
            source=src,
        )
    def measured(r, c):
        """(l, s) of RPC pixel (r, c): the model's 2x2 system solved."""
        dr, dc = r - a0, c - b0
        return ((1.0 + b2) * dr - a2 * dc) / det, (-b1 * dr + (1.0 + a1) * dc) / det

    def forward(l, s):
        return l + a0 + a1 * l + a2 * s, s + b0 + b1 * l + b2 * s

    if image_shape is not None:
        window = (0.0, float(image_shape[0]), 0.0, float(image_shape[1]))
    else:
        r0, r1, c0, c1 = rpc.image_window()
        ml, ms = measured(np.array([r0, r0, r1, r1]), np.array([c0, c1, c0, c1]))
        window = (ml.min(), ml.max(), ms.min(), ms.max())
    if h_range is None:
        h_range = (rpc.height_off - abs(rpc.height_scale), rpc.height_off + abs(rpc.height_scale))
    # the measured window's corners in this RPC's frame, for the ground box
    w0, w1, v0, v1 = window
    fr, fc = forward(np.array([w0, w0, w1, w1]), np.array([v0, v1, v0, v1]))
    lon_r, lat_r = rpc.ground_box((fr.min(), fr.max(), fc.min(), fc.max()), h_range)

    def corrected(lon, lat, h):
        return measured(*rpc.project(lon, lat, h))

    return fit_rpc(
        corrected, lon_r, lat_r, tuple(h_range), image_window=window, max_error=max_error, source=src,
    )
