"""Per-cell uncertainty of a displacement component, from stable terrain
(pure numpy / scipy).

The approach of DEM-differencing error analysis (Hugonnet et al. 2022,
doi:10.1109/JSTARS.2022.3188922), applied to each component:

1. **Heteroscedastic part**: the spread of the stable residual depends on
   predictors (slope, correlation quality); the stable cells are binned by
   quantiles of each predictor and the robust spread in a bin,
   ``sqrt(median**2 + q68**2)`` (``q68``: 68.3rd percentile of the absolute
   deviation from the median; a bias counts as error), is the sigma of
   every cell falling in that bin (:func:`binned_sigma`).
2. **Spatially correlated part**: an empirical variogram of the residual
   standardised by that sigma, fitted with a nugget plus one spherical
   model (:func:`fit_variogram`); the error of a mean over a set of cells
   (a strip along a fault) adds the average correlation between its cells
   (:func:`mean_error`) instead of dividing by ``sqrt(N)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["binned_sigma", "Variogram", "fit_variogram", "mean_error", "coverage"]


def _robust_spread(v: np.ndarray) -> float:
    """``hypot(median, q68)``: the bias and the 68.3rd percentile of the
    absolute deviation from the median (the standard deviation for Gaussian
    errors; unlike the NMAD, it follows moderately heavy tails)."""
    med = float(np.median(v))
    return float(np.hypot(med, np.percentile(np.abs(v - med), 68.27)))


def binned_sigma(residual: np.ndarray, stable: np.ndarray, predictors: dict[str, np.ndarray],
                 bins: int = 5, min_count: int = 30) -> tuple[np.ndarray, dict]:
    """Sigma of every cell from the stable residual binned by ``predictors``.

    Parameters
    ----------
    residual : ndarray
        Displacement minus its expected value on stable terrain (0 after
        correction), metres, NaN = none.
    stable : ndarray of bool
    predictors : dict of name -> ndarray
        Same shape; the bins are the quantiles of each over the stable
        cells (a joint grid of ``bins**k`` bins). A bin with fewer than
        ``min_count`` stable cells takes the spread of its bin of the
        first predictor, else of the whole stable set.
    bins : int
        Quantile bins per predictor.

    Returns
    -------
    sigma : ndarray
        Metres, NaN where the residual or a predictor is NaN.
    table : dict
        The bin edges and the sigma and count of each bin.
    """
    use = stable & np.isfinite(residual)
    for p in predictors.values():
        use &= np.isfinite(p)
    total = _robust_spread(residual[use]) if use.any() else np.nan
    names = list(predictors)
    edges, index = {}, []
    for name in names:
        p = predictors[name]
        e = np.unique(np.quantile(p[use], np.linspace(0, 1, bins + 1))) if use.any() else np.array([0.0, 1.0])
        e[0], e[-1] = -np.inf, np.inf
        edges[name] = e
        index.append(np.clip(np.searchsorted(e, np.nan_to_num(p), side="right") - 1, 0, len(e) - 2))
    shape = tuple(len(edges[n]) - 1 for n in names)
    flat = np.ravel_multi_index(index, shape)
    nb = int(np.prod(shape))
    sig = np.full(nb, total)
    cnt = np.bincount(flat[use], minlength=nb)
    r_use, f_use = residual[use], flat[use]
    for b in np.flatnonzero(cnt >= min_count):
        sig[b] = _robust_spread(r_use[f_use == b])
    # sparse joint bins: the one-predictor bin of the first predictor (the strongest, by the caller's order)
    if len(names) > 1:
        first = index[0][use]
        for b in np.flatnonzero(cnt < min_count):
            i0 = np.unravel_index(b, shape)[0]
            sel = first == i0
            if sel.sum() >= min_count:
                sig[b] = _robust_spread(r_use[sel])
    sigma = sig[flat]
    valid = np.isfinite(residual)
    for p in predictors.values():
        valid &= np.isfinite(p)
    sigma = np.where(valid, sigma, np.nan)
    table = {"predictors": names, "edges": {n: [float(v) for v in edges[n][1:-1]] for n in names},
             "sigma": sig.reshape(shape).tolist(), "count": cnt.reshape(shape).tolist(), "all_stable": total}
    return sigma, table


@dataclass(frozen=True)
class Variogram:
    """Nugget + spherical model of a standardised residual:
    ``gamma(h) = nugget + sill * (1.5 h/range - 0.5 (h/range)**3)`` for
    ``h < range``, ``nugget + sill`` beyond (``h`` metres)."""

    nugget: float
    sill: float
    range_m: float

    def correlation(self, h: np.ndarray) -> np.ndarray:
        """Covariance of two cells ``h`` metres apart (``h > 0``), in units of
        the standardised variance."""
        t = np.clip(np.asarray(h, float) / max(self.range_m, 1e-9), 0, 1)
        return self.sill * (1 - (1.5 * t - 0.5 * t**3))

    def to_dict(self) -> dict:
        return {"nugget": self.nugget, "sill": self.sill, "range_m": self.range_m}


def fit_variogram(z: np.ndarray, x: np.ndarray, y: np.ndarray, use: np.ndarray, *, samples: int = 3000,
                  seed: int = 0, max_lag: float | None = None) -> tuple[Variogram, dict]:
    """Empirical variogram of ``z`` (standardised residual) over ``use`` cells,
    from the pairs of ``samples`` random cells, fitted by a nugget plus a
    spherical model. ``x`` columns / ``y`` rows in metres."""
    from scipy.optimize import curve_fit

    X, Y = np.broadcast_arrays(np.asarray(x, float)[None, :], np.asarray(y, float)[:, None])
    sel = np.flatnonzero((use & np.isfinite(z)).ravel())
    rng = np.random.default_rng(seed)
    pick = rng.choice(sel, size=min(samples, sel.size), replace=False)
    zx, xx, yy = z.ravel()[pick], X.ravel()[pick], Y.ravel()[pick]
    i, j = np.triu_indices(pick.size, 1)
    h = np.hypot(xx[i] - xx[j], yy[i] - yy[j])
    g = 0.5 * (zx[i] - zx[j]) ** 2
    max_lag = max_lag or float(np.percentile(h, 50))
    edges = np.linspace(0, max_lag, 21)
    k = np.digitize(h, edges) - 1
    lag, gam, cnt = [], [], []
    for b in range(len(edges) - 1):
        m = k == b
        if m.sum() >= 20:
            lag.append(float(h[m].mean()))
            gam.append(float(np.mean(g[m])))
            cnt.append(int(m.sum()))
    lag, gam = np.array(lag), np.array(gam)
    var = float(np.var(zx))

    def model(hh, n, s, a):
        t = np.clip(hh / a, 0, 1)
        return n + s * (1.5 * t - 0.5 * t**3)

    try:
        (n, s, a), _ = curve_fit(model, lag, gam, p0=(0.5 * var, 0.5 * var, max_lag / 3),
                                 bounds=([0, 0, 1e-6], [4 * var + 1e-9, 4 * var + 1e-9, 10 * max_lag]))
    except (RuntimeError, ValueError):
        n, s, a = var, 0.0, float(edges[1])
    return Variogram(float(n), float(s), float(a)), {"lag_m": lag.tolist(), "gamma": gam.tolist(), "count": cnt}


def mean_error(sigma: np.ndarray, x: np.ndarray, y: np.ndarray, cells: np.ndarray, vario: Variogram,
               *, samples: int = 2000, seed: int = 0) -> float:
    """Standard error of the mean of a component over ``cells``: the mean
    sigma there times ``sqrt((nugget + sill)/N + mean correlation of two
    distinct cells)`` (the average over random pairs)."""
    X, Y = np.broadcast_arrays(np.asarray(x, float)[None, :], np.asarray(y, float)[:, None])
    sel = np.flatnonzero((cells & np.isfinite(sigma)).ravel())
    if sel.size == 0:
        return float("nan")
    s = float(np.sqrt(np.mean(sigma.ravel()[sel] ** 2)))
    n = sel.size
    rng = np.random.default_rng(seed)
    a = rng.choice(sel, size=samples)
    b = rng.choice(sel, size=samples)
    d = np.hypot(X.ravel()[a] - X.ravel()[b], Y.ravel()[a] - Y.ravel()[b])
    rho = float(np.mean(vario.correlation(d[d > 0]))) if (d > 0).any() else vario.sill
    return s * float(np.sqrt((vario.nugget + vario.sill) / n + rho))


def coverage(error: np.ndarray, sigma: np.ndarray, k: float = 2.0) -> float:
    """Share of cells whose ``|error| <= k * sigma`` (where both are finite)."""
    ok = np.isfinite(error) & np.isfinite(sigma)
    return float(np.mean(np.abs(error[ok]) <= k * sigma[ok])) if ok.any() else float("nan")
