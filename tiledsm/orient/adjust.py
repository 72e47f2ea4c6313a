"""Bias-compensated RPC block adjustment (pure kernel on arrays).

Unknowns: per image the terms of its bias model (:mod:`tiledsm.orient.bias`:
``A0, B0`` or ``A0..B2``), and per point its ground coordinates, as metric
offsets (east, north, up; metres) from a starting position. Observations,
each a residual divided by its standard deviation:

- image measurements ``(l, s)`` of tie points, GCPs:
  ``RPC_i(ground) - (l + A0 + A1 l + A2 s)`` (and the sample equation),
  pixels;
- GCP ground coordinates (a prior on the point's offsets), metres;
- optionally a reference DEM on tie-point heights:
  ``h - DEM(lon, lat)``, metres (the DEM-assisted RFM block adjustment of
  Zhang et al. 2016, "DEM-assisted RFM block adjustment of pushbroom
  nadir viewing HRS imagery", IEEE TGRS 54(2), 1025-1034), each with the
  standard deviation ``sqrt(dem_sigma_m**2 + slope_i**2)``: ``slope_i`` the
  DEM's representativeness error at the point (cell size x gradient,
  :attr:`Block.dem_slope_sigma_m`). The DEM fixes the block's datum through
  the weighted *mean* of these residuals, so those of buildings, trees and
  of ground beside them (a coarse cell averages both) must be rejected:
  their distribution is skewed, and a fixed threshold of metres keeps a
  biased tail. After every solve the residuals' scatter ``s0`` is
  re-estimated (1.4826 x their median absolute deviation) and those beyond
  ``dem_reject_k * s0`` of their median are dropped (the weights stay
  those of ``dem_sigma_m``: DEM errors are correlated in space, and the
  scatter would make a few hundred points outweigh GCPs). One more unknown, the
  DEM's overall vertical offset (prior :attr:`AdjustParams.dem_offset_sigma_m`
  around 0), takes the DEM's own bias when GCPs fix the datum (the DEM's
  point scatter ``s0`` says nothing of it); without GCPs moving the block
  is cheaper and the offset stays 0: the DEM is the datum;
- a weak prior on every bias term (zero, :attr:`AdjustParams.prior_shift_px`
  / :attr:`AdjustParams.prior_linear`): it fixes the datum when nothing
  absolute is observed (tie points only) and is negligible otherwise.

Solved by :func:`scipy.optimize.least_squares` (trust region reflective,
LSMR on the sparse Jacobian, robust ``soft_l1`` loss), then observations
whose residual exceeds :attr:`AdjustParams.reject_k` times the median
residual (and at least :attr:`AdjustParams.min_reject_px`) are rejected and
the block is solved again (at most one measurement per point and round, the
worst; a measurement rejected earlier whose residual is now below the
threshold is taken back), until nothing changes.

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0));
lon/lat WGS84 degrees; heights metres above the WGS84 ellipsoid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from tiledsm.errors import MatchingError
from tiledsm.geometry.rpc import RPC
from tiledsm.orient.bias import BiasModel
from tiledsm.orient.spec import AdjustParams

__all__ = ["Block", "AdjustResult", "adjust_block", "intersect", "METRES_PER_DEGREE"]

#: metres per degree of latitude (spherical, WGS84 semi-major axis): the
#: local parametrisation of ground offsets (any consistent value works)
METRES_PER_DEGREE = 6378137.0 * np.pi / 180.0

DemFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Block:
    """The observations of a block adjustment.

    Attributes
    ----------
    img, pt : numpy.ndarray
        ``(m,)`` int: image and point index of each image measurement.
    row, col : numpy.ndarray
        ``(m,)`` measured pixel coordinates (GDAL convention).
    sigma_px : numpy.ndarray
        ``(m,)`` standard deviation of each measurement, pixels.
    ground0 : numpy.ndarray
        ``(n, 3)`` starting lon, lat, h of each point (for GCPs: their
        surveyed coordinates).
    prior_sigma_m : numpy.ndarray
        ``(n,)`` standard deviation of the ground coordinates of each point,
        metres; ``inf`` for tie points (free).
    use_dem : numpy.ndarray
        ``(n,)`` bool: the point's height is observed on the reference DEM.
    point_ids : numpy.ndarray
        ``(n,)`` str, for reports.
    dem_slope_sigma_m : numpy.ndarray, optional
        ``(n,)`` representativeness error of the reference DEM at each
        point, metres (e.g.
        :meth:`tiledsm.orient.dem.ReferenceDEM.slope_sigma`), added in
        quadrature to the DEM's noise; None: 0.
    """

    img: np.ndarray
    pt: np.ndarray
    row: np.ndarray
    col: np.ndarray
    sigma_px: np.ndarray
    ground0: np.ndarray
    prior_sigma_m: np.ndarray
    use_dem: np.ndarray
    point_ids: np.ndarray
    dem_slope_sigma_m: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(self.ground0.shape[0])


@dataclass(frozen=True)
class AdjustResult:
    """Outcome of :func:`adjust_block`.

    Attributes
    ----------
    x : list of numpy.ndarray
        Estimated bias terms of each image (in its model's term order).
    ground : numpy.ndarray
        ``(n, 3)`` adjusted lon, lat, h of each point.
    residual_px : numpy.ndarray
        ``(m, 2)`` final image residuals (projected minus corrected
        measurement), pixels, rejected measurements included.
    rejected : numpy.ndarray
        ``(m,)`` bool, measurements rejected as blunders.
    dem_used : numpy.ndarray
        ``(n,)`` bool, DEM height observations kept.
    dem_residual_m : numpy.ndarray
        ``(n,)`` ``h - DEM`` at the solution (NaN without DEM).
    rounds, nfev : int
    """

    x: list
    ground: np.ndarray
    residual_px: np.ndarray
    rejected: np.ndarray
    dem_used: np.ndarray
    dem_residual_m: np.ndarray
    rounds: int
    nfev: int
    info: dict = field(default_factory=dict)


def _lonlat(g0: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground position of metric offsets ``d`` (n, 3) from ``g0``."""
    coslat = np.cos(np.radians(g0[:, 1]))
    return (g0[:, 0] + d[:, 0] / (METRES_PER_DEGREE * coslat), g0[:, 1] + d[:, 1] / METRES_PER_DEGREE,
            g0[:, 2] + d[:, 2])


def _project_obs(rpcs: Sequence[RPC], img: np.ndarray, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
    r = np.full(img.shape, np.nan)
    c = np.full(img.shape, np.nan)
    for i, rpc in enumerate(rpcs):
        m = img == i
        if m.any():
            r[m], c[m] = rpc.project(lon[m], lat[m], h[m])
    return r, c


def _project_with_partials(rpcs, img, g0, d, step: float = 1.0):
    """Projections of the points of each measurement and their derivatives
    with respect to the (east, north, up) offsets, pixels per metre
    (central differences of ``step`` metres)."""
    lon, lat, h = _lonlat(g0, d)
    r, c = _project_obs(rpcs, img, lon, lat, h)
    jr = np.empty(img.shape + (3,))
    jc = np.empty(img.shape + (3,))
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        lp, ap, hp = _lonlat(g0, d + e)
        lm, am, hm = _lonlat(g0, d - e)
        rp, cp = _project_obs(rpcs, img, lp, ap, hp)
        rm, cm = _project_obs(rpcs, img, lm, am, hm)
        jr[:, k] = (rp - rm) / (2 * step)
        jc[:, k] = (cp - cm) / (2 * step)
    return r, c, jr, jc


def intersect(
    rpcs: Sequence[RPC],
    img: np.ndarray,
    pt: np.ndarray,
    row: np.ndarray,
    col: np.ndarray,
    n_points: int,
    h0: np.ndarray | float | None = None,
    n_iter: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view space intersection (Gauss-Newton, vectorised over points).

    Parameters
    ----------
    rpcs : sequence of RPC
    img, pt, row, col : numpy.ndarray
        ``(m,)`` measurements (image index, point index, GDAL row/col).
    n_points : int
    h0 : float or (n,) array, optional
        Starting heights (default: the first camera's ``height_off``).
    n_iter : int

    Returns
    -------
    ground : numpy.ndarray
        ``(n, 3)`` lon, lat, h; NaN for points seen in fewer than 2 images.
    residual : numpy.ndarray
        ``(m, 2)`` reprojection residual (projected minus measured), pixels.
    """
    img, pt = np.asarray(img, int), np.asarray(pt, int)
    row, col = np.asarray(row, float), np.asarray(col, float)
    nobs = np.bincount(pt, minlength=n_points)
    first = np.full(n_points, -1)
    order = np.argsort(pt, kind="stable")
    first[pt[order[::-1]]] = order[::-1]
    ok = nobs >= 2
    hstart = np.broadcast_to(np.asarray(rpcs[0].height_off if h0 is None else h0, float), (n_points,)).copy()
    g0 = np.full((n_points, 3), np.nan)
    for i, rpc in enumerate(rpcs):
        m = ok & (first >= 0)
        m[m] = img[first[m]] == i
        if m.any():
            f = first[m]
            lon, lat = rpc.localize(row[f], col[f], hstart[m])
            g0[m] = np.column_stack([lon, lat, hstart[m]])
    use = ok[pt]
    d = np.zeros((n_points, 3))
    gg = np.where(np.isfinite(g0), g0, 0.0)
    for _ in range(n_iter):
        r, c, jr, jc = _project_with_partials(rpcs, img[use], gg[pt[use]], d[pt[use]])
        er, ec = row[use] - r, col[use] - c
        ata = np.zeros((n_points, 3, 3))
        atb = np.zeros((n_points, 3))
        p = pt[use]
        np.add.at(ata, p, jr[:, :, None] * jr[:, None, :] + jc[:, :, None] * jc[:, None, :])
        np.add.at(atb, p, jr * er[:, None] + jc * ec[:, None])
        ata[~ok] = np.eye(3)
        ata += np.eye(3) * 1e-9
        step = np.linalg.solve(ata, atb[..., None])[..., 0]
        d += step
        if np.nanmax(np.abs(step)) < 1e-4:
            break
    lon, lat, h = _lonlat(gg, d)
    ground = np.column_stack([lon, lat, h])
    ground[~ok] = np.nan
    rr, cc = _project_obs(rpcs, img, ground[pt, 0], ground[pt, 1], ground[pt, 2])
    return ground, np.column_stack([rr - row, cc - col])


class _Problem:
    """Residuals and sparse Jacobian of one solve."""

    def __init__(self, rpcs, models, block: Block, dem: DemFn | None, params: AdjustParams,
                 active: np.ndarray, dem_active: np.ndarray, dem_sigma: np.ndarray):
        self.rpcs, self.models, self.b, self.dem, self.p = rpcs, models, block, dem, params
        self.active = active.astype(float)
        self.dem_active = dem_active
        self.dem_sigma = dem_sigma
        sizes = [m.size for m in models]
        self.param_off = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.n_params = int(self.param_off[-1])
        self.off_col = self.n_params + 3 * block.n_points  # the DEM's vertical offset
        self.n_unknown = self.off_col + 1
        self.prior_pts = np.flatnonzero(np.isfinite(block.prior_sigma_m))
        self.dem_pts = np.flatnonzero(dem_active) if dem is not None else np.zeros(0, int)
        # parameter prior sigmas
        ps = []
        for m in models:
            ps += [params.prior_shift_px if t in ("A0", "B0") else params.prior_linear for t in m.terms]
        self.param_sigma = np.array(ps, float)

    def split(self, x):
        return x[: self.n_params], x[self.n_params: self.off_col].reshape(-1, 3)

    def _dem(self, lon, lat):
        return np.asarray(self.dem(lon, lat), float)

    def evaluate(self, x, with_jac: bool):
        b, p = self.b, self.p
        xp, d = self.split(x)
        g0 = b.ground0[b.pt]
        if with_jac:
            r, c, jr, jc = _project_with_partials(self.rpcs, b.img, g0, d[b.pt])
        else:
            lon, lat, h = _lonlat(g0, d[b.pt])
            r, c = _project_obs(self.rpcs, b.img, lon, lat, h)
        lhs_r = np.empty_like(r)
        lhs_c = np.empty_like(c)
        w = self.active / b.sigma_px
        rows, cols, vals = [], [], []
        m_obs = len(b.img)
        for i, model in enumerate(self.models):
            m = b.img == i
            if not m.any():
                continue
            xi = xp[self.param_off[i]: self.param_off[i + 1]]
            lhs_r[m], lhs_c[m] = model.correction(xi, b.row[m], b.col[m])
            if with_jac:
                dr, dc = model.design(b.row[m], b.col[m])
                idx = np.flatnonzero(m)
                pcol = self.param_off[i] + np.arange(model.size)
                for k in range(model.size):
                    rows += [idx, idx + m_obs]
                    cols += [np.full(idx.size, pcol[k]), np.full(idx.size, pcol[k])]
                    vals += [-dr[:, k] * w[idx], -dc[:, k] * w[idx]]
        res = [(r - lhs_r) * w, (c - lhs_c) * w]
        if with_jac:
            idx = np.arange(m_obs)
            for k in range(3):
                col_k = self.n_params + 3 * b.pt + k
                rows += [idx, idx + m_obs]
                cols += [col_k, col_k]
                vals += [jr[:, k] * w, jc[:, k] * w]
        n_row = 2 * m_obs
        # ground priors of GCPs
        pp = self.prior_pts
        if pp.size:
            s = b.prior_sigma_m[pp]
            res.append((d[pp] / s[:, None]).ravel())
            if with_jac:
                for k in range(3):
                    rows.append(n_row + 3 * np.arange(pp.size) + k)
                    cols.append(self.n_params + 3 * pp + k)
                    vals.append(1.0 / s)
            n_row += 3 * pp.size
        # reference DEM on tie-point heights
        dp = self.dem_pts
        if dp.size:
            lon, lat, h = _lonlat(b.ground0[dp], d[dp])
            z = self._dem(lon, lat)
            ds = self.dem_sigma[dp]
            res.append((h - z - x[self.off_col]) / ds)
            if with_jac:
                st = 5.0
                coslat = np.cos(np.radians(b.ground0[dp, 1]))
                ze = (self._dem(lon + st / (METRES_PER_DEGREE * coslat), lat)
                      - self._dem(lon - st / (METRES_PER_DEGREE * coslat), lat)) / (2 * st)
                zn = (self._dem(lon, lat + st / METRES_PER_DEGREE) - self._dem(lon, lat - st / METRES_PER_DEGREE)) / (2 * st)
                ze, zn = np.nan_to_num(ze), np.nan_to_num(zn)
                ar = n_row + np.arange(dp.size)
                for k, v in enumerate((-ze, -zn, np.ones(dp.size))):
                    rows.append(ar)
                    cols.append(self.n_params + 3 * dp + k)
                    vals.append(v / ds)
                rows.append(ar)
                cols.append(np.full(dp.size, self.off_col))
                vals.append(-1.0 / ds)
            n_row += dp.size
        res.append(np.array([x[self.off_col] / p.dem_offset_sigma_m]))
        if with_jac:
            rows.append(np.array([n_row]))
            cols.append(np.array([self.off_col]))
            vals.append(np.array([1.0 / p.dem_offset_sigma_m]))
        n_row += 1
        # weak priors on the bias terms
        res.append(xp / self.param_sigma)
        if with_jac:
            rows.append(n_row + np.arange(self.n_params))
            cols.append(np.arange(self.n_params))
            vals.append(1.0 / self.param_sigma)
        n_row += self.n_params
        f = np.nan_to_num(np.concatenate(res), nan=0.0)
        if not with_jac:
            return f
        jac = sp.csr_matrix((np.nan_to_num(np.concatenate(vals)), (np.concatenate(rows), np.concatenate(cols))),
                            shape=(n_row, self.n_unknown))
        return f, jac


def adjust_block(
    rpcs: Sequence[RPC],
    models: Sequence[BiasModel],
    block: Block,
    dem: DemFn | None = None,
    params: AdjustParams = AdjustParams(),
) -> AdjustResult:
    """Estimate the bias terms of every image and the ground coordinates of
    every point (see module docstring).

    Parameters
    ----------
    rpcs : sequence of RPC
        The images' (biased) cameras.
    models : sequence of BiasModel
        The bias model of each image.
    block : Block
    dem : callable, optional
        ``dem(lon, lat) -> h`` (metres, WGS84 ellipsoidal; NaN where
        unknown): the reference DEM constraining the heights of the points
        with ``block.use_dem``.
    params : AdjustParams
        Weights and robustness (:class:`~tiledsm.orient.spec.AdjustParams`:
        ``OrientSpec.adjust``, ``orient.adjust`` in a recipe).

    Returns
    -------
    AdjustResult

    Raises
    ------
    MatchingError
        No measurement at all, or a point index out of range.
    """
    if len(block.img) == 0:
        raise MatchingError("block adjustment: no image measurements")
    if block.pt.max() >= block.n_points:
        raise MatchingError("block adjustment: point index out of range")
    active = np.ones(len(block.img), bool)
    dem_active = np.asarray(block.use_dem, bool).copy()
    if dem is not None and dem_active.any():
        z = np.asarray(dem(block.ground0[dem_active, 0], block.ground0[dem_active, 1]), float)
        dem_active[np.flatnonzero(dem_active)[~np.isfinite(z)]] = False
    dem_candidates = dem_active.copy()
    slope = (np.zeros(block.n_points) if block.dem_slope_sigma_m is None
             else np.nan_to_num(np.asarray(block.dem_slope_sigma_m, float)))
    s0 = float(params.dem_sigma_m)
    sizes = sum(m.size for m in models)
    x = np.zeros(sizes + 3 * block.n_points + 1)
    nfev = 0
    rounds = 0
    for rounds in range(1, params.max_rounds + 1):
        dem_sigma = np.hypot(params.dem_sigma_m, slope)
        prob = _Problem(rpcs, models, block, dem, params, active, dem_active, dem_sigma)
        sol = least_squares(
            lambda v: prob.evaluate(v, False), x, jac=lambda v: prob.evaluate(v, True)[1],
            method="trf", tr_solver="lsmr", loss=params.loss, f_scale=params.f_scale, x_scale="jac",
            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=200,
        )
        x, nfev = sol.x, nfev + sol.nfev
        res = _image_residuals(rpcs, models, block, x, prob)
        norm = np.hypot(res[:, 0], res[:, 1])
        thr = max(params.min_reject_px, params.reject_k * float(np.median(norm[active])))
        new = active & (norm > thr)
        if new.any():  # one measurement per point and round: the worst (its partners absorb part of it)
            cand = np.flatnonzero(new)
            order = cand[np.argsort(-norm[cand], kind="stable")]
            _, first = np.unique(block.pt[order], return_index=True)
            new[:] = False
            new[order[first]] = True
        dem_new = np.zeros_like(dem_active)
        dem_back = np.zeros_like(dem_active)
        s0_changed = False
        if dem is not None and dem_active.any():
            dres = _dem_residuals(block, x, prob, dem) - x[prob.off_col]
            if params.dem_robust_sigma:
                r = dres[dem_active]
                r = r[np.isfinite(r)]  # a point that moved off the DEM
                r = r if r.size else np.zeros(1)
                s_new = max(params.dem_min_sigma_m, 1.4826 * float(np.median(np.abs(r - np.median(r)))))
                s0_changed = abs(s_new - s0) > 0.2 * s0
                s0 = s_new
                centre = float(np.median(r))
            else:
                centre = 0.0
            within = np.abs(dres - centre) <= params.dem_reject_k * s0
            dem_new = dem_active & ~within
            dem_back = dem_candidates & ~dem_active & within
        back = ~active & (norm <= thr)  # rejected earlier, fine now that the blunders are out
        if not new.any() and not dem_new.any() and not back.any() and not dem_back.any() and not s0_changed:
            break
        active = (active & ~new) | back
        dem_active = (dem_active & ~dem_new) | dem_back
    xs = [x[prob.param_off[i]: prob.param_off[i + 1]].copy() for i in range(len(models))]
    _, d = prob.split(x)
    lon, lat, h = _lonlat(block.ground0, d)
    dres = _dem_residuals(block, x, prob, dem) if dem is not None else np.full(block.n_points, np.nan)
    return AdjustResult(
        x=xs, ground=np.column_stack([lon, lat, h]), residual_px=res, rejected=~active, dem_used=dem_active,
        dem_residual_m=dres, rounds=rounds, nfev=nfev,
        info={"cost": float(sol.cost), "status": int(sol.status), "dem_sigma_m": s0 if dem is not None else None,
              "dem_offset_m": float(x[prob.off_col]) if dem is not None else None},
    )


def _image_residuals(rpcs, models, block: Block, x, prob: _Problem) -> np.ndarray:
    xp, d = prob.split(x)
    lon, lat, h = _lonlat(block.ground0[block.pt], d[block.pt])
    r, c = _project_obs(rpcs, block.img, lon, lat, h)
    out = np.empty((len(block.img), 2))
    for i, model in enumerate(models):
        m = block.img == i
        if m.any():
            lr, lc = model.correction(xp[prob.param_off[i]: prob.param_off[i + 1]], block.row[m], block.col[m])
            out[m, 0], out[m, 1] = r[m] - lr, c[m] - lc
    return out


def _dem_residuals(block: Block, x, prob: _Problem, dem: DemFn) -> np.ndarray:
    _, d = prob.split(x)
    lon, lat, h = _lonlat(block.ground0, d)
    out = np.full(block.n_points, np.nan)
    m = np.asarray(block.use_dem, bool)
    if m.any():
        out[m] = h[m] - np.asarray(dem(lon[m], lat[m]), float)
    return out
