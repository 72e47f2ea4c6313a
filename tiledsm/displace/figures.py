"""Quick-looks of a 3D displacement field (matplotlib ``Figure`` on Agg).

- :func:`displacement_figure`: horizontal displacement as arrows over the
  hillshade of the pre-event DSM, the colour of the arrows their length
  (colour bar, metres), and ``dU`` beside it (diverging colour bar);
- :func:`profile_figure`: fault-parallel, fault-perpendicular and vertical
  displacement against the signed distance to the fault trace, with the
  offsets read at the fault.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tiledsm.io import atomic_path

__all__ = ["displacement_figure", "profile_figure"]


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def displacement_figure(dE: np.ndarray, dN: np.ndarray, dU: np.ndarray | None,
                        extent: tuple[float, float, float, float], path: str | Path, *,
                        shade: np.ndarray | None = None, title: str = "", arrows: int = 32,
                        fault_line: tuple[np.ndarray, np.ndarray] | None = None,
                        shade_extent: tuple[float, float, float, float] | None = None) -> Path:
    """Arrows of ``(dE, dN)`` over ``shade`` and the ``dU`` map (``dU``
    None: the map of the horizontal displacement's length instead).

    ``extent`` is ``(left, right, bottom, top)`` metres; arrays ``(y, x)``
    with row 0 north; about ``arrows`` arrows per side; ``shade`` (values
    0..1) spans ``shade_extent`` (default ``extent``).
    """
    from matplotlib.figure import Figure

    ny, nx = dE.shape
    fig = Figure(figsize=(13, 6), dpi=100)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    if shade is not None:
        ax1.imshow(shade, cmap="gray", extent=shade_extent or extent, vmin=0, vmax=1, interpolation="bilinear")
    k = max(1, int(round(max(ny, nx) / arrows)))
    ys = np.arange(k // 2, ny, k)
    xs = np.arange(k // 2, nx, k)
    left, right, bottom, top = extent
    cx = left + (xs + 0.5) * (right - left) / nx
    cy = top - (ys + 0.5) * (top - bottom) / ny
    u, v = dE[np.ix_(ys, xs)], dN[np.ix_(ys, xs)]
    mag = np.hypot(u, v)
    hi = float(np.nanpercentile(mag, 98)) if np.isfinite(mag).any() else 1.0
    X, Y = np.meshgrid(cx, cy)
    q = ax1.quiver(X, Y, u, v, mag, cmap="viridis", clim=(0, max(hi, 1e-3)), angles="xy", scale_units="xy",
                   scale=max(hi, 1e-3) / (0.8 * k * (right - left) / nx), width=0.004)
    fig.colorbar(q, ax=ax1, shrink=0.8, label="horizontal displacement (m)")
    if dU is not None:
        lim = float(np.nanpercentile(np.abs(dU), 98)) if np.isfinite(dU).any() else 1.0
        im = ax2.imshow(np.ma.masked_invalid(dU), cmap="RdBu_r", vmin=-lim, vmax=lim, extent=extent,
                        interpolation="nearest")
        fig.colorbar(im, ax=ax2, shrink=0.8, label="dU, vertical displacement (m)")
    else:
        length = np.hypot(dE, dN)
        im = ax2.imshow(np.ma.masked_invalid(length), cmap="viridis", vmin=0, vmax=max(hi, 1e-3), extent=extent,
                        interpolation="nearest")
        fig.colorbar(im, ax=ax2, shrink=0.8, label="horizontal displacement (m; blank: NaN)")
    for ax in (ax1, ax2):
        if fault_line is not None:
            ax.plot(*fault_line, "k--", lw=1)
        ax.set_xlim(left, right)
        ax.set_ylim(bottom, top)
        ax.set_xlabel("easting (m)")
    ax1.set_ylabel("northing (m)")
    ax1.set_title("dE, dN (arrows, length to scale)")
    ax2.set_title("dU" if dU is not None else "|(dE, dN)|")
    if title:
        fig.suptitle(title)
    return _save(fig, Path(path))


def profile_figure(profiles: dict, offsets: dict, path: str | Path, title: str = "") -> Path:
    """Binned medians against the distance to the fault (``profiles``: ``distance_m``
    and one list per component, metres) with each offset and its error."""
    from matplotlib.figure import Figure

    names = [n for n in ("along_strike", "across_strike", "dU") if n in profiles]
    fig = Figure(figsize=(7, 2.4 * len(names)), dpi=100)
    d = np.asarray(profiles["distance_m"], float)
    for i, name in enumerate(names):
        ax = fig.add_subplot(len(names), 1, i + 1)
        ax.plot(d, np.asarray(profiles[name], float), ".-", ms=3)
        if "truth_" + name in profiles:
            ax.plot(d, np.asarray(profiles["truth_" + name], float), "k-", lw=0.8, label="truth")
            ax.legend(loc="best", fontsize=8)
        ax.axvline(0, color="k", ls="--", lw=0.8)
        o = offsets.get(name)
        lab = f"{name} (m)"
        if o is not None:
            lab += f"\noffset {o['offset']:+.3f} ± {o['error']:.3f}"
        ax.set_ylabel(lab, fontsize=8)
        ax.grid(alpha=0.3)
    ax.set_xlabel("signed distance to the fault trace (m; + right block)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, Path(path))
