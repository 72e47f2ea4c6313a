"""The datum of a block adjusted on tie points alone.

Tie points see only how the views agree with one another: moving the whole
ground by a translation ``t`` (east, north, up; metres) and every view's
image shift by ``J_i t`` (``J_i``: the view's pixels per metre, 2 x 3)
leaves every tie residual unchanged. Something else must choose ``t``.
The adjustment's weak priors choose the least squares of the corrections,
which spreads one view's error over all of them: with view 1 of three
off by (5.4, -3.8) px, the corrections came out (1.09, 0.67), (0.61,
-2.14), (-1.89, 1.13) px, view 1 relative to view 0 only (-0.49, -2.82):
the along-track part (parallax direction) went into a height translation of
the whole block, about -20 m on the DSM. The tie points themselves had
measured the one observable combination right (rows x0 + x1 - 2 x2 = 5.56
px on a 256-px scene for 5.4 injected): the relative orientation was
fine, the datum was not.

:func:`consensus_datum` holds fixed the two views that agree best (the
least-squares misfit of holding both at zero correction; pairs with the
first, reference, view preferred on a tie, and the reference held exactly
in its pairs): every view that agrees with them keeps its RPC, a view that
disagrees takes the whole correction. For a pair of images this is the
reference view held fixed and the other corrected across the epipolar
direction only (as s2p's pointing correction).

Measured (``tests/orient/test_datum.py``: 3 views, 512 px, GSD 0.5 m, B/H
0.15, view 1's RPC off by (5.4, -3.8) px; DSM - truth median / NMAD): true
RPCs 0.055 / 0.681 m, biased -19.57 / 0.862 m; after ``tiledsm orient``
with the weak priors alone -19.57 / 0.791 m, with the mean rule
-19.62 / 0.795 m, with consensus 0.253 / 0.679 m (view 1 corrected by
(5.455, -3.851) px; on the unbiased views orient finds (0.055, -0.051) px
there: the tie points' own error). The least sum of correction lengths (an
L1 "median") is not enough: on a 256-px scene it still left -14.1 m,
spreading the along-track part over two views being shorter than one.
Absolute accuracy still needs GCPs or a DEM: if the agreeing views share
one bias, the block keeps it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tiledsm.geometry.rpc import RPC

__all__ = ["ground_jacobians", "consensus_datum", "mean_datum", "DATUMS", "DATUM_RULES"]



def ground_jacobians(rpcs: Sequence[RPC], lon: float, lat: float, h: float, step_m: float = 1.0) -> np.ndarray:
    """``(n, 2, 3)``: each view's (row, col) change per metre east, north
    and up at one ground point (central differences of ``step_m``)."""
    m_per_deg_lat = 6378137.0 * np.pi / 180.0
    m_per_deg_lon = m_per_deg_lat * np.cos(np.radians(lat))
    moves = [(step_m / m_per_deg_lon, 0.0, 0.0), (0.0, step_m / m_per_deg_lat, 0.0), (0.0, 0.0, step_m)]
    out = np.empty((len(rpcs), 2, 3))
    for i, rpc in enumerate(rpcs):
        for k, (dlon, dlat, dh) in enumerate(moves):
            rp, cp = rpc.project(np.array([lon + dlon]), np.array([lat + dlat]), np.array([h + dh]))
            rm, cm = rpc.project(np.array([lon - dlon]), np.array([lat - dlat]), np.array([h - dh]))
            out[i, :, k] = [(float(rp[0]) - float(rm[0])) / (2 * step_m), (float(cp[0]) - float(cm[0])) / (2 * step_m)]
    return out


def consensus_datum(shifts: np.ndarray, jacobians: np.ndarray, reference: int = 0, tie_px: float = 0.05,
                    reference_weight: float = 1e3, min_conditioning: float = 0.1) -> np.ndarray:
    """The ground translation ``t`` (metres east, north, up) that holds the
    two best-agreeing views at zero correction (module docstring).

    Parameters
    ----------
    shifts : (n, 2) array
        Each view's image correction ``(A0, B0)``, pixels.
    jacobians : (n, 2, 3) array
        :func:`ground_jacobians`.
    reference : int
        The view preferred (and held exactly) in its pairs.
    tie_px : float
        Misfits within this many pixels of the best count as a tie.
    reference_weight : float
        Weight of the reference's equations against the other view's.
    min_conditioning : float
        Pairs whose ``[J_i; J_j]`` has a ratio of extreme singular values
        below this fraction of the best pair's are not considered (same
        viewing direction: the pair leaves the height free).

    Returns
    -------
    numpy.ndarray
        ``(3,)`` metres; the corrections become ``shifts + jacobians @ t``.
    """
    x = np.asarray(shifts, float)
    J = np.asarray(jacobians, float)
    n = len(x)
    if n == 1:
        return np.linalg.lstsq(J[0], -x[0], rcond=None)[0]
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    # a pair seen from (nearly) the same direction (two epochs of one orbit) cannot hold a height: only pairs
    # whose geometry fixes a translation nearly as well as the best pair's are candidates
    conditioning = {}
    for i, j in pairs:
        sv = np.linalg.svd(np.vstack([J[i], J[j]]), compute_uv=False)
        conditioning[i, j] = sv[-1] / sv[0]
    best_conditioning = max(conditioning.values())
    fits = []
    for i, j in pairs:
        if conditioning[i, j] < min_conditioning * best_conditioning:
            continue
        w = np.repeat([reference_weight if k == reference else 1.0 for k in (i, j)], 2)
        t = np.linalg.lstsq(np.vstack([J[i], J[j]]) * w[:, None], -np.concatenate([x[i], x[j]]) * w, rcond=None)[0]
        misfit = float(np.hypot(*(x[i] + J[i] @ t)) + np.hypot(*(x[j] + J[j] @ t)))
        fits.append((misfit, reference not in (i, j), t))
    best = min(f[0] for f in fits)
    return min((f for f in fits if f[0] <= best + tie_px), key=lambda f: (f[1], f[0]))[2]


def mean_datum(shifts: np.ndarray, jacobians: np.ndarray, reference: int = 0) -> np.ndarray:
    """The ground translation minimising ``sum_i |shifts[i] + jacobians[i] @ t|**2``:
    the views' mean correction held at zero (as nearly as a ground
    translation can)."""
    J = np.asarray(jacobians, float)
    return np.linalg.lstsq(J.reshape(-1, 3), -np.asarray(shifts, float).reshape(-1), rcond=None)[0]


#: datum rules of a tie-point-only block: name -> t(shifts, jacobians); "priors" keeps the adjustment's own
#: (the least squares of all bias terms, linear ones included)
DATUMS = {"consensus": consensus_datum, "mean": mean_datum, "priors": None}

#: what each rule means, for orient.json and the log
DATUM_RULES = {
    "consensus": "the two views that agree best held at zero correction (the first view preferred on a tie): "
                 "views that agree keep their RPCs, one that disagrees takes the correction",
    "mean": "the ground translation that leaves the views' mean image correction at zero (least squares)",
    "priors": "the adjustment's weak priors on every bias term (least squares of all terms)",
}
