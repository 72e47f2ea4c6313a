"""Removal of what is not ground motion from a displacement field, fitted
on stable terrain (pure numpy).

Two terms, each estimated on the cells declared stable and removed
everywhere:

- a **plane** ``a + b*x + c*y`` per component (the residual frame offset
  and tilt between the two orthoimages: orientation and DSM datum
  leftovers), fitted by iteratively re-weighted least squares (cells
  beyond 3 NMAD of the current fit are dropped, 5 passes);
- optionally **stripes** along rows (``stripes="rows"``): the median of the
  stable residual of every row, smoothed over ``stripe_rows`` rows, as the
  along-track signature of attitude jitter of a pushbroom sensor flying
  north-south (rows of a north-up grid are across-track lines).

Coordinates ``x, y`` are cell centres in metres (the grid's CRS); values in
metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from tiledsm.errors import TiledsmError

__all__ = ["CorrectionParams", "NoStableCellsError", "fit_plane", "row_stripes", "correct_component"]


class NoStableCellsError(TiledsmError):
    """No valid displacement is left on the stable terrain after masking."""


@dataclass(frozen=True)
class CorrectionParams:
    """What :func:`correct_component` removes.

    Attributes
    ----------
    plane : bool
        Fit and remove ``a + b x + c y`` (else only the median ``a``).
    stripes : {None, "rows"}
        Also remove along-row stripes.
    stripe_rows : int
        Rows of the running median smoothing the stripe profile.
    min_cells : int
        Fewest stable cells accepted.
    """

    plane: bool = True
    stripes: str | None = None
    stripe_rows: int = 3
    min_cells: int = 30


def fit_plane(values: np.ndarray, x: np.ndarray, y: np.ndarray, use: np.ndarray, plane: bool = True) -> np.ndarray:
    """Robust ``(a, b, c)`` of ``values ~ a + b (x - x̄) + c (y - ȳ)`` over ``use``;
    ``x`` columns, ``y`` rows (broadcast to ``values``). ``b = c = 0`` when
    ``plane`` is False. Returns ``(a, b, c, x̄, ȳ)``."""
    X, Y = np.broadcast_arrays(np.asarray(x, float)[None, :], np.asarray(y, float)[:, None])
    sel = use & np.isfinite(values)
    v, xs, ys = values[sel], X[sel], Y[sel]
    xm, ym = float(xs.mean()), float(ys.mean())
    keep = np.ones(v.size, bool)
    coef = np.array([float(np.median(v)), 0.0, 0.0])
    for _ in range(5):
        if plane:
            A = np.column_stack([np.ones(keep.sum()), xs[keep] - xm, ys[keep] - ym])
            coef = np.linalg.lstsq(A, v[keep], rcond=None)[0]
        else:
            coef = np.array([float(np.median(v[keep])), 0.0, 0.0])
        r = v - (coef[0] + coef[1] * (xs - xm) + coef[2] * (ys - ym))
        med = np.median(r[keep])
        nmad = 1.4826 * np.median(np.abs(r[keep] - med))
        new = np.abs(r - med) <= 3 * max(nmad, 1e-9)
        if (new == keep).all() or new.sum() < 3:
            break
        keep = new
    return np.array([coef[0], coef[1], coef[2], xm, ym])


def row_stripes(residual: np.ndarray, use: np.ndarray, rows: int) -> np.ndarray:
    """Median stable residual of every row, smoothed by a running median of
    ``rows``; rows without a stable cell take the nearest row's value."""
    ok = use & np.isfinite(residual)
    prof = np.full(residual.shape[0], np.nan)
    for i in np.flatnonzero(ok.any(axis=1)):
        prof[i] = np.median(residual[i, ok[i]])
    have = np.isfinite(prof)
    if not have.any():
        return np.zeros(residual.shape[0])
    idx = ndimage.distance_transform_edt(~have, return_distances=False, return_indices=True)[0]
    prof = prof[idx]
    return ndimage.median_filter(prof, size=max(1, rows), mode="nearest")


def correct_component(values: np.ndarray, x: np.ndarray, y: np.ndarray, stable: np.ndarray,
                      params: CorrectionParams = CorrectionParams(), name: str = "displacement") -> tuple[np.ndarray, dict]:
    """``values`` minus the plane (and stripes) fitted on ``stable`` cells.

    Returns
    -------
    corrected : ndarray
    report : dict
        The plane (``offset`` at the stable centroid, ``slope_x``,
        ``slope_y`` per metre), the stripe profile's standard deviation,
        and the stable cells' median/NMAD before and after.

    Raises
    ------
    NoStableCellsError
        Fewer than ``params.min_cells`` stable cells hold a value.
    """
    use = np.asarray(stable, bool) & np.isfinite(values)
    n = int(use.sum())
    if n < params.min_cells:
        raise NoStableCellsError(
            f"{name}: {n} stable cell(s) hold a displacement (need {params.min_cells}): the stable mask leaves no "
            "stable terrain with texture; shrink the excluded polygons or check that both orthos see it")
    a, b, c, xm, ym = fit_plane(values, x, y, use, params.plane)
    X, Y = np.broadcast_arrays(np.asarray(x, float)[None, :], np.asarray(y, float)[:, None])
    out = values - (a + b * (X - xm) + c * (Y - ym))
    rep = {"offset": float(a), "slope_x_per_m": float(b), "slope_y_per_m": float(c), "centroid": [xm, ym],
           "stable_cells": n}
    if params.stripes == "rows":
        prof = row_stripes(out, use, params.stripe_rows)
        out = out - prof[:, None]
        rep["stripes"] = {"along": "rows", "std": float(np.std(prof)), "max_abs": float(np.max(np.abs(prof)))}
    elif params.stripes is not None:
        raise ValueError(f"stripes: None or 'rows', got {params.stripes!r}")

    def stats(v):
        v = v[use]
        med = float(np.median(v))
        return {"median": med, "nmad": float(1.4826 * np.median(np.abs(v - med)))}

    rep["stable_before"] = stats(values)
    rep["stable_after"] = stats(out)
    return out, rep
