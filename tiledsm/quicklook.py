"""Quick-look PNGs of DSMs, difference maps and images (orthoimages) (matplotlib ``Figure`` objects
rendered by Agg: no pyplot, no display, no global backend change).

Conventions
-----------
- Arrays are ``(y, x)`` with row 0 at the north (ground grids) or the image
  top (sensor geometry); x grows east / right.
- Hillshade azimuth is degrees clockwise from north (315 = light from the
  north-west), altitude degrees above the horizon.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import xarray as xr

from tiledsm.io import atomic_path

__all__ = ["hillshade", "quicklook", "KINDS", "NAN_COLOUR"]

#: supported quick-look kinds
KINDS = ("height", "difference", "image")

#: colour of cells with no value
NAN_COLOUR = (0.85, 0.25, 0.85, 1.0)


def hillshade(
    z: np.ndarray,
    resolution: float | tuple[float, float] = 1.0,
    azimuth: float = 315.0,
    altitude: float = 45.0,
    z_factor: float = 1.0,
) -> np.ndarray:
    """Lambertian shading of a height grid.

    ``shade = max(0, n . l)`` with ``n`` the unit surface normal from
    central-difference slopes (one-sided at the edges, ``numpy.gradient``)
    and ``l`` the unit vector towards the light.

    Parameters
    ----------
    z : (ny, nx) array
        Heights, metres; NaN allowed: the shade is NaN at NaN cells and at
        their 4 neighbours (whose central differences use them).
    resolution : float or (dy, dx)
        Cell size, metres (positive; rows run south).
    azimuth, altitude : float
        Light direction, degrees (clockwise from north; above horizon).
    z_factor : float
        Vertical exaggeration.

    Returns
    -------
    numpy.ndarray
        ``float64`` shade in [0, 1].
    """
    z = np.asarray(z, dtype=float) * z_factor
    dy, dx = (resolution, resolution) if np.isscalar(resolution) else resolution
    dz_drow, dz_dcol = np.gradient(z, float(dy), float(dx))
    p = dz_dcol  # dz/d(east)
    q = -dz_drow  # dz/d(north): rows run south
    az, alt = math.radians(azimuth), math.radians(altitude)
    lx, ly, lz = math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)
    with np.errstate(invalid="ignore"):
        shade = (-p * lx - q * ly + lz) / np.sqrt(1.0 + p * p + q * q)
    shade = np.clip(shade, 0.0, 1.0)
    shade[~np.isfinite(z)] = np.nan
    return shade


def _cell_size(da: xr.DataArray) -> tuple[float, float]:
    out = []
    for dim in ("y", "x"):
        c = da.coords.get(dim)
        out.append(abs(float(c[1] - c[0])) if c is not None and c.size > 1 else 1.0)
    return out[0], out[1]


def _reduce(arrays: list[xr.DataArray], max_size: int) -> list[tuple[np.ndarray, tuple[float, float]]]:
    """Each array block-meaned down to at most ``max_size`` cells per side,
    with its cell size: lazy until the small results, which are computed
    together, so a huge dask DSM is never loaded whole and is read once for
    a difference and its shading."""
    import dask

    lazy, cells = [], []
    for da in arrays:
        if da.ndim != 2:
            raise ValueError(f"quicklook: expected a 2-D (y, x) array, got dims {da.dims}")
        if da.dims != ("y", "x"):
            da = da.rename(dict(zip(da.dims, ("y", "x"))))
        dy, dx = _cell_size(da)
        f = max(1, math.ceil(max(da.shape) / max_size))
        if f > 1:
            da = da.coarsen(y=f, x=f, boundary="trim").mean()
        lazy.append(da.data)
        cells.append((dy * f, dx * f))
    return [(np.asarray(z, dtype=float), c) for z, c in zip(dask.compute(*lazy), cells)]


def _figure(shape: tuple[int, int], figsize, dpi):
    from matplotlib.figure import Figure

    if figsize is None:
        ny, nx = shape
        w = 8.0
        figsize = (w, float(np.clip(w * 0.85 * ny / max(nx, 1), 2.5, 12.0)))
    fig = Figure(figsize=figsize, dpi=dpi)
    return fig, fig.add_subplot(1, 1, 1)


def quicklook(
    da: xr.DataArray,
    path: str | os.PathLike,
    kind: str = "height",
    title: str | None = None,
    dsm: xr.DataArray | None = None,
    *,
    max_size: int = 1024,
    figsize: tuple[float, float] | None = None,
    dpi: int = 100,
    percentile: float = 98.0,
) -> Path:
    """Write a quick-look PNG, atomically.

    Parameters
    ----------
    da : DataArray
        ``(y, x)`` heights (``kind="height"``) or height differences
        (``kind="difference"``), metres; NaN for no value.
    path : path-like
        Output ``.png``.
    kind : {"height", "difference"}
        ``"height"``: hillshade blended with a terrain colour map, colour bar
        in metres. ``"difference"``: diverging colour map with symmetric
        limits ``+-P`` where ``P`` is the ``percentile`` of ``|da|``, over
        the hillshade of ``dsm`` when given. ``"image"``: grey levels
        (digital numbers) stretched between the ``100 - percentile`` and
        ``percentile`` percentiles.
    title : str, optional
    dsm : DataArray, optional
        Heights on the same grid, shaded under a difference map.
    max_size : int
        Larger arrays are block-averaged to at most this many cells a side.
    figsize, dpi
        Figure size (inches) and resolution: the PNG is
        ``figsize * dpi`` pixels. Default width 8 in, height from the aspect.
    percentile : float
        Robust limit for differences (and colour range of heights: the
        ``100 - percentile`` .. ``percentile`` range).

    Notes
    -----
    Cells without a value are drawn in :data:`NAN_COLOUR` (magenta).
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    if kind not in KINDS:
        raise ValueError(f"quicklook: kind must be one of {KINDS}, got {kind!r}")
    shaded = kind == "difference" and dsm is not None
    (z, (dy, dx)), *under = _reduce([da, dsm] if shaded else [da], max_size)
    fig, ax = _figure(z.shape, figsize, dpi)
    finite = np.isfinite(z)
    ny, nx = z.shape
    extent = (0, nx, ny, 0)
    if kind == "height":
        shade = hillshade(np.where(finite, z, np.nanmean(z) if finite.any() else 0.0), (dy, dx))
        lo, hi = (np.nanpercentile(z, [100 - percentile, percentile]) if finite.any() else (0.0, 1.0))
        hi = hi if hi > lo else lo + 1.0
        cmap = colormaps["terrain"]
        rgb = cmap(np.clip((z - lo) / (hi - lo), 0, 1))[..., :3]
        rgb = rgb * (0.35 + 0.65 * shade[..., None])
        rgba = np.concatenate([rgb, np.ones(z.shape + (1,))], axis=-1)
        rgba[~finite] = NAN_COLOUR
        ax.imshow(rgba, extent=extent, interpolation="nearest")
        mappable = ScalarMappable(norm=Normalize(lo, hi), cmap=cmap)
        label = "height (m)"
    elif kind == "image":
        lo, hi = (np.nanpercentile(z, [100 - percentile, percentile]) if finite.any() else (0.0, 1.0))
        hi = hi if hi > lo else lo + 1.0
        cmap = colormaps["gray"].with_extremes(bad=NAN_COLOUR)
        mappable = ax.imshow(np.ma.masked_invalid(z), cmap=cmap, vmin=lo, vmax=hi, extent=extent, interpolation="nearest")
        label = "digital number"
    else:
        if shaded:
            h, (hy, hx) = under[0]
            hf = np.isfinite(h)
            shade = hillshade(np.where(hf, h, np.nanmean(h) if hf.any() else 0.0), (hy, hx))
            ax.imshow(np.where(hf, shade, np.nan), cmap="gray", vmin=0, vmax=1, extent=extent, interpolation="nearest")
        lim = float(np.nanpercentile(np.abs(z), percentile)) if finite.any() else 1.0
        lim = lim if lim > 0 else 1.0
        cmap = colormaps["RdBu_r"].with_extremes(bad=NAN_COLOUR)
        mappable = ax.imshow(
            np.ma.masked_invalid(z), cmap=cmap, vmin=-lim, vmax=lim, extent=extent,
            alpha=0.75 if dsm is not None else 1.0, interpolation="nearest",
        )
        label = "difference (m)"
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title)
    cb = fig.colorbar(mappable, ax=ax, shrink=0.85, fraction=0.05, pad=0.02)
    cb.set_label(label)
    final = Path(path)
    with atomic_path(final) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return final
