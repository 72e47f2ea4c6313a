"""DSM co-registration: Nuth & Kääb (2011) horizontal shift + vertical bias.

Nuth, C. and Kääb, A. (2011), Co-registration and bias corrections of
satellite elevation data sets for quantifying glacier thickness change,
The Cryosphere 5, 271-290, https://doi.org/10.5194/tc-5-271-2011.

Sign conventions (those of demcompare's output)
-----------------------------------------------
The result is the correction **applied to the other (secondary) DSM** so it
lies on the reference:

``other_corrected[i, j] = other(i - dy_px, j - dx_px) + dz``

i.e. ``dx_px`` moves the other DSM's content by ``+dx_px`` columns and
``dy_px`` by ``+dy_px`` rows (south on a north-up grid); ``dz`` (metres) is
added to its heights. In ground units ``dx = dx_px * transform.a`` and
``dy = dy_px * transform.e`` (CRS units; degrees for a geographic CRS, and
``dy`` is negative when the content moves south); ``dx_m``/``dy_m`` are the
same shift in metres east/north. Example: demcompare's SRTM pair, where
``sec[i, j] = ref[i + 5, j + 3]``, gives ``dx_px = 3, dy_px = 5``.

Methods are registered by name in :data:`COREG_METHODS` ("nuth_kaab",
"none"); an optional planar deramp is fitted after either.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from tiledsm.compare.shift import ShiftKernelError, kernel_taps, shift_array, shift_halo, shifted_at
from tiledsm.compare.terrain import slope_aspect
from tiledsm.errors import TiledsmError
from tiledsm.recipes import StrictModel

__all__ = [
    "CoregFitSpec",
    "Coregistration",
    "FitWindow",
    "CoregistrationError",
    "NoStableTerrainError",
    "COREG_METHODS",
    "register_coreg",
    "get_coreg",
    "shift_array",
    "shift_halo",
    "fit_deramp",
    "nmad",
    "shifted_at",
]


class CoregistrationError(TiledsmError):
    """Raised when co-registration cannot be estimated."""


class NoStableTerrainError(CoregistrationError):
    """Raised when no stable terrain is left to fit the co-registration."""


def nmad(values: np.ndarray) -> float:
    """Normalised median absolute deviation, ``1.4826 * median(|v - median(v)|)``."""
    v = np.asarray(values, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


# --------------------------------------------------------------------------- parameters, fit data & result
class CoregFitSpec(StrictModel):
    """Parameters of the co-registration fit, ``compare.coreg_fit`` of a
    recipe: Nuth & Kääb's iterations, the samples they use, the subpixel
    shift. Its outlier rule is ``compare.nmad_k``, its deramp
    ``compare.deramp`` (the methods' other arguments)."""

    max_iterations: int = Field(10, ge=1, description="Nuth & Kääb iterations at most")
    tolerance_px: float = Field(0.005, ge=0, description="stop when the shift update is below this, pixels")
    vertical: Literal["median", "mean"] = Field(
        "median", description="statistic of the stable dh (inliers) giving the vertical bias")
    min_slope_deg: float = Field(
        1.0, ge=0, description="flattest reference slope (degrees) of the samples of the horizontal fit: "
        "flat cells carry no shift information")
    max_slope_deg: float = Field(
        70.0, le=90, description="steepest reference slope (degrees) of the samples of the horizontal fit "
        "(the statistics' stable terrain is compare.max_slope_deg)")
    aspect_bins: int = Field(72, ge=3, description="aspect sectors whose median dh / tan(slope) is fitted")
    min_bin_count: int = Field(20, ge=1, description="sectors with fewer samples are ignored")
    shift_kernel: str = Field("cubic", description="subpixel interpolation of the shifted DSM: cubic or linear")
    max_samples: int = Field(
        500_000, ge=0, description="the iterations use at most this many of the candidate cells (stable, slope in "
        "range), an evenly strided subset; 0: all of them (the exact fit). The median, NMAD and vertical bias use "
        "every stable cell")

    @field_validator("shift_kernel")
    @classmethod
    def _known_kernel(cls, value: str) -> str:
        try:
            kernel_taps(0.5, value)
        except ShiftKernelError as exc:
            raise ValueError(str(exc)) from None
        return value

    @model_validator(mode="after")
    def _slope_range(self):
        if not self.min_slope_deg < self.max_slope_deg:
            raise ValueError(f"need min_slope_deg < max_slope_deg, got {self.min_slope_deg} and {self.max_slope_deg}")
        return self


@dataclass(frozen=True)
class FitWindow:
    """A window of the common grid loaded in memory for the fit.

    Attributes
    ----------
    ref, other : ndarray
        Heights (metres, NaN = none) of the window, same shape.
    stable : ndarray of bool
        Cells allowed in the fit (polygon exclusions already applied).
    step_x, step_y : ndarray
        Signed metres east per column / north per row, shape ``(rows, 1)``
        (see :mod:`tiledsm.compare.terrain`).
    row0, col0 : int
        Position of the window in the common grid (for the deramp).
    """

    ref: np.ndarray
    other: np.ndarray
    stable: np.ndarray
    step_x: np.ndarray
    step_y: np.ndarray
    row0: int = 0
    col0: int = 0


@dataclass(frozen=True)
class Coregistration:
    """A fitted co-registration (see the module notes for the signs).

    Attributes
    ----------
    method : str
    dx_px, dy_px : float
        Shift applied to the other DSM, in columns / rows.
    dz : float
        Vertical offset added to the other DSM (metres), at the ramp origin.
    ramp_col, ramp_row : float
        Planar deramp added to the other DSM, metres per column / row, about
        ``ramp_origin`` (row, col) of the common grid (zero without deramp).
    iterations : int
    converged : bool
    n_samples : int
        Stable samples in the last iteration.
    median_before, nmad_before, median_after, nmad_after : float
        Stable-terrain ``dh = other - ref`` (metres) before and after.
    history : tuple
        ``(dx_px, dy_px)`` after each iteration.
    """

    method: str
    dx_px: float = 0.0
    dy_px: float = 0.0
    dz: float = 0.0
    ramp_col: float = 0.0
    ramp_row: float = 0.0
    ramp_origin: tuple[float, float] = (0.0, 0.0)
    iterations: int = 0
    converged: bool = True
    n_samples: int = 0
    median_before: float = float("nan")
    nmad_before: float = float("nan")
    median_after: float = float("nan")
    nmad_after: float = float("nan")
    history: tuple = field(default_factory=tuple)

    def vertical_field(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Vertical correction (metres) added to the other DSM at grid ``rows, cols``."""
        r0, c0 = self.ramp_origin
        return self.dz + self.ramp_col * (cols - c0) + self.ramp_row * (rows - r0)

    def ground(self, crs, transform, step_x: float, step_y: float) -> dict:
        """Shift in CRS units and metres (east/north), for ``metrics.json``.

        ``step_x``/``step_y``: signed metres per column/row at the grid centre.
        """
        units = "degree" if crs.is_geographic else (crs.linear_units or "metre")
        return {
            "dx": self.dx_px * transform.a,
            "dy": self.dy_px * transform.e,
            "dz": self.dz,
            "dx_px": self.dx_px,
            "dy_px": self.dy_px,
            "dx_m": self.dx_px * float(step_x),
            "dy_m": self.dy_px * float(step_y),
            "units": {"dx": units, "dy": units, "dz": "m", "dx_m": "m east", "dy_m": "m north"},
        }

    def to_dict(self) -> dict:
        d = asdict(self)
        d["history"] = [list(h) for h in self.history]
        d["ramp_origin"] = list(self.ramp_origin)
        return d


# --------------------------------------------------------------------------- registry
CoregFn = Callable[[list, CoregFitSpec, float, bool], Coregistration]
#: name -> fit function ``fn(windows: list[FitWindow], fit: CoregFitSpec, nmad_k: float, deramp: bool) ->
#: Coregistration``: ``nmad_k`` is the outlier rule (``|dh - median| > nmad_k x NMAD``), ``deramp`` says a plane
#: is fitted after (and removed before each horizontal fit); the recipe's ``compare.coreg_fit``, ``compare.nmad_k``
#: and ``compare.deramp``
COREG_METHODS: dict[str, CoregFn] = {}


def register_coreg(name: str) -> Callable[[CoregFn], CoregFn]:
    """Decorator adding a co-registration method; refuses duplicate names."""

    def deco(fn: CoregFn) -> CoregFn:
        if name in COREG_METHODS:
            raise ValueError(f"co-registration method {name!r} is already registered")
        COREG_METHODS[name] = fn
        return fn

    return deco


def get_coreg(name: str) -> CoregFn:
    """The registered method ``name`` (error listing the known names)."""
    try:
        return COREG_METHODS[name]
    except KeyError:
        raise CoregistrationError(f"unknown co-registration method {name!r}: one of {sorted(COREG_METHODS)}") from None


# --------------------------------------------------------------------------- fitting helpers
def _samples(windows, shift, dz, kernel: str, with_position: bool = False):
    """Pool ``dh`` of stable, valid cells, the other DSM shifted by ``shift``
    with ``kernel`` (and their grid ``rows``, ``cols`` ``with_position``,
    else ``None``)."""
    dhs, rows, cols = [], [], []
    for w in windows:
        moved = w.other if shift == (0.0, 0.0) else shift_array(w.other, shift[0], shift[1], kernel)
        dh = moved.astype(np.float64) + dz - w.ref
        ok = w.stable & np.isfinite(dh)
        dhs.append(dh[ok])
        del dh
        if with_position:
            r, c = np.nonzero(ok)
            rows.append(r + w.row0)
            cols.append(c + w.col0)
    cat = lambda xs: np.concatenate(xs) if xs else np.empty(0)  # noqa: E731
    return cat(dhs), (cat(rows) if with_position else None), (cat(cols) if with_position else None)


def _inliers(dh: np.ndarray, k: float) -> np.ndarray:
    med = np.median(dh)
    s = nmad(dh)
    if s == 0:
        return np.abs(dh - med) <= 1e-9
    return np.abs(dh - med) <= k * s


def _mean_steps(windows) -> tuple[float, float]:
    sx = np.concatenate([np.broadcast_to(w.step_x, (w.ref.shape[0], 1)).ravel() for w in windows])
    sy = np.concatenate([np.broadcast_to(w.step_y, (w.ref.shape[0], 1)).ravel() for w in windows])
    return float(sx.mean()), float(sy.mean())


def _require_samples(n: int, what: str):
    if n == 0:
        raise NoStableTerrainError(
            f"no stable terrain left for {what}: every cell is NaN, excluded by the stable-terrain "
            "polygons, or outside the slope range"
        )


def _plane(dh: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Least-squares plane ``p0 + p1*col + p2*row`` of ``dh``, evaluated at the samples."""
    r0, c0 = rows.mean(), cols.mean()
    design = np.column_stack([np.ones_like(dh), cols - c0, rows - r0])
    coef, *_ = np.linalg.lstsq(design, dh, rcond=None)
    return design @ coef


def _vertical(dh: np.ndarray, statistic: str) -> float:
    return float(np.median(dh) if statistic == "median" else np.mean(dh))


# --------------------------------------------------------------------------- methods
@register_coreg("none")
def fit_none(windows: list[FitWindow], fit: CoregFitSpec, nmad_k: float, deramp: bool) -> Coregistration:
    """No co-registration: zero shift and zero vertical offset (statistics only)."""
    dh, *_ = _samples(windows, (0.0, 0.0), 0.0, fit.shift_kernel)
    _require_samples(dh.size, "the difference statistics")
    med, s = float(np.median(dh)), nmad(dh)
    return Coregistration("none", n_samples=int(dh.size), median_before=med, nmad_before=s, median_after=med, nmad_after=s)


@dataclass(frozen=True)
class _Candidates:
    """The cells of one window that may enter the horizontal fit (stable,
    slope within range), fixed across iterations: their flat indices, the
    tangent of their slope and their aspect sector."""

    index: np.ndarray
    tan_slope: np.ndarray
    sector: np.ndarray


def _strided(indices: list[np.ndarray], max_samples: int) -> list[np.ndarray]:
    """Every ``stride``-th of the windows' flat ``indices`` (the same stride in
    each window) so at most ~``max_samples`` remain; all of them with 0."""
    total = sum(i.size for i in indices)
    stride = max(1, -(-total // max_samples)) if max_samples else 1
    return [i[::stride] for i in indices]


def _dh_at(windows, indices: list[np.ndarray], shift, kernel: str) -> list[np.ndarray]:
    """Per window, ``dh = other(shifted) - ref`` (float64) at its flat ``indices``
    (the arithmetic of :func:`_samples`, NaN kept)."""
    out = []
    for w, index in zip(windows, indices):
        if shift == (0.0, 0.0):
            moved = w.other.ravel()[index]
        else:
            moved = shifted_at(w.other, index, shift[0], shift[1], kernel)
        out.append(moved.astype(np.float64) + 0.0 - w.ref.ravel()[index])
    return out


def _finite(dhs: list[np.ndarray]) -> np.ndarray:
    """The finite values of ``dhs``, pooled in order."""
    return np.concatenate([d[np.isfinite(d)] for d in dhs]) if dhs else np.empty(0)


def _candidates(windows, fit: CoregFitSpec, edges: np.ndarray) -> list[_Candidates]:
    """Per window, the stable cells within the slope range (slope and aspect of
    the reference, :func:`slope_aspect`), every ``stride``-th of them when
    there are more than ``fit.max_samples``; the full-window slope and
    aspect are dropped at once, so the fit holds a few numbers per sample."""
    found = []
    for w in windows:
        slope, aspect = slope_aspect(w.ref, w.step_x, w.step_y)
        index = np.flatnonzero(w.stable & (slope >= fit.min_slope_deg) & (slope <= fit.max_slope_deg))
        found.append((index, slope.ravel()[index], aspect.ravel()[index]))
        del slope, aspect
    kept = _strided([np.arange(f[0].size) for f in found], fit.max_samples)
    out = []
    for (index, slope, aspect), k in zip(found, kept):
        index, slope, aspect = index[k], slope[k], aspect[k]
        sector = np.clip(np.digitize(aspect, edges) - 1, 0, fit.aspect_bins - 1)
        out.append(_Candidates(index, np.tan(np.deg2rad(slope)), sector.astype(np.int16)))
    return out


def _candidate_samples(windows, cands: list[_Candidates], shift, kernel: str, with_position: bool):
    """``(dh, tan_slope, sector, rows, cols)`` of the candidates whose
    ``dh = other(shifted) - ref`` is finite, pooled window by window in row-major
    order (with every candidate: the cells, order and values of
    :func:`_samples`); the shifted DSM is interpolated at the candidates only
    (:func:`shifted_at`). ``rows``/``cols`` only ``with_position``, else ``None``."""
    dhs, tans, sectors, rows, cols = [], [], [], [], []
    for w, c, dh in zip(windows, cands, _dh_at(windows, [c.index for c in cands], shift, kernel)):
        ok = np.isfinite(dh)
        dhs.append(dh[ok])
        tans.append(c.tan_slope[ok])
        sectors.append(c.sector[ok])
        if with_position:
            r, col = np.divmod(c.index[ok], w.ref.shape[1])
            rows.append(r + w.row0)
            cols.append(col + w.col0)
    cat = lambda xs: np.concatenate(xs) if xs else np.empty(0)  # noqa: E731
    return cat(dhs), cat(tans), cat(sectors), (cat(rows) if with_position else None), (cat(cols) if with_position else None)


@register_coreg("nuth_kaab")
def fit_nuth_kaab(windows: list[FitWindow], fit: CoregFitSpec, nmad_k: float, deramp: bool) -> Coregistration:
    """Nuth & Kääb (2011) iterative shift + vertical bias on stable terrain.

    Each iteration shifts the other DSM by the current estimate (subpixel,
    :func:`shift_array`), takes ``dh = other - ref`` on stable cells within
    the slope range, drops ``|dh - median| > nmad_k * NMAD`` outliers,
    removes the median (vertical bias; a plane with ``deramp``), and fits the median of ``dh / tan(slope)`` in aspect sectors with
    ``a * cos(b - aspect) + c`` — linear in ``(a cos b, a sin b, c)``, solved
    by least squares. ``(a sin b, a cos b)`` is the remaining displacement of
    the other DSM (metres east, north), converted to pixels and subtracted.
    Slope and aspect come from the reference DSM: the candidate cells, their
    slope's tangent and aspect sector are taken once (:func:`_candidates`),
    so an iteration only shifts and differences. The vertical bias is the
    median (or mean) stable ``dh`` after the last shift. ``fit`` holds the
    iterations, slope range, sectors, samples and shift kernel.
    """
    p, k, kernel = fit, nmad_k, fit.shift_kernel
    # every stable cell, not a subsample: on integer heights (SRTM) the NMAD of a subsample can jump by a
    # whole metre, and the outlier rule of the stable terrain (k x NMAD) with it
    stable = [np.flatnonzero(w.stable) for w in windows]
    dh0 = _finite(_dh_at(windows, stable, (0.0, 0.0), kernel))
    _require_samples(dh0.size, "co-registration")
    med0 = float(np.median(dh0))
    nmad0 = nmad(dh0)
    del dh0
    sx, sy = _mean_steps(windows)
    dy_px = dx_px = 0.0
    history = []
    converged = False
    edges = np.linspace(0.0, 2 * np.pi, p.aspect_bins + 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    cands = _candidates(windows, p, edges)
    it = 0
    for it in range(1, p.max_iterations + 1):
        dh, tan_slope, sector, rows, cols = _candidate_samples(windows, cands, (dy_px, dx_px), kernel, deramp)
        _require_samples(dh.size, "the Nuth & Kääb fit (slope range)")
        keep = _inliers(dh, k)
        # remove the current vertical bias (or plane) first: bias / tan(slope) is not a constant
        resid = dh[keep] - (_plane(dh[keep], rows[keep], cols[keep]) if deramp else np.median(dh[keep]))
        target = resid / tan_slope[keep]
        idx = sector[keep]
        order = np.argsort(idx, kind="stable")
        idx_s, tgt_s = idx[order], target[order]
        starts = np.searchsorted(idx_s, np.arange(p.aspect_bins + 1))
        meds, angs = [], []
        for b in range(p.aspect_bins):
            seg = tgt_s[starts[b] : starts[b + 1]]
            if seg.size >= p.min_bin_count:
                meds.append(np.median(seg))
                angs.append(centres[b])
        if len(meds) < 3:
            raise NoStableTerrainError(
                f"Nuth & Kääb fit: only {len(meds)} aspect sectors hold >= {p.min_bin_count} stable samples "
                "(need 3); the stable terrain is too small or too flat"
            )
        angs = np.asarray(angs)
        design = np.column_stack([np.cos(angs), np.sin(angs), np.ones_like(angs)])
        (s_n, s_e, _c), *_ = np.linalg.lstsq(design, np.asarray(meds), rcond=None)
        d_col = -s_e / sx
        d_row = -s_n / sy
        dx_px += d_col
        dy_px += d_row
        history.append((dx_px, dy_px))
        if math.hypot(d_col, d_row) < p.tolerance_px:
            converged = True
            break
    del cands
    dh = _finite(_dh_at(windows, stable, (dy_px, dx_px), kernel))
    _require_samples(dh.size, "the vertical bias")
    inl = _inliers(dh, k)
    dz = -_vertical(dh[inl], p.vertical) + 0.0
    after = dh + dz
    return Coregistration(
        "nuth_kaab",
        dx_px=float(dx_px),
        dy_px=float(dy_px),
        dz=float(dz),
        iterations=it,
        converged=converged,
        n_samples=int(inl.sum()),
        median_before=med0,
        nmad_before=nmad0,
        median_after=float(np.median(after)),
        nmad_after=nmad(after),
        history=tuple(history),
    )


def fit_deramp(windows: list[FitWindow], coreg: Coregistration, fit: CoregFitSpec, nmad_k: float,
               origin: tuple[float, float]) -> Coregistration:
    """Add a planar correction ``dz + ramp_col*(col-c0) + ramp_row*(row-r0)``.

    Fitted by least squares to the stable inlier ``dh`` left after ``coreg``
    (its shift applied); replaces ``coreg.dz``. ``origin`` is ``(r0, c0)``,
    normally the grid centre, so ``dz`` stays the offset there. ``fit``
    gives the shift kernel, ``nmad_k`` the outliers left out.
    """
    dh, rows, cols = _samples(windows, (coreg.dy_px, coreg.dx_px), 0.0, fit.shift_kernel, with_position=True)
    _require_samples(dh.size, "the deramp")
    rows, cols = rows - origin[0], cols - origin[1]
    keep = _inliers(dh + coreg.dz, nmad_k)
    design = np.column_stack([np.ones(keep.sum()), cols[keep], rows[keep]])
    (p0, pc, pr), *_ = np.linalg.lstsq(design, dh[keep], rcond=None)
    after = dh - (p0 + pc * cols + pr * rows)
    return Coregistration(
        **{
            **asdict(coreg),
            "method": coreg.method + "+deramp",
            "dz": float(-p0),
            "ramp_col": float(-pc),
            "ramp_row": float(-pr),
            "ramp_origin": (float(origin[0]), float(origin[1])),
            "median_after": float(np.median(after)),
            "nmad_after": nmad(after),
            "n_samples": int(keep.sum()),
            "history": coreg.history,
        }
    )
