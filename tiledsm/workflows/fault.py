"""A fault and what is measured across it, pure functions on arrays: its
trace and signed distances (:class:`Fault`), the throw of a displacement
map across it (:func:`throw_across`), error statistics, the synthetic
event's rupture polygons (excluded from stable terrain) and the
co-registration expected when the "stable" terrain moved.

Conventions: map coordinates in the grid's CRS (metres); a trace's right
side is the side of its right-hand normal.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from tiledsm.errors import TiledsmError

__all__ = ["Fault", "throw_across", "strip_values", "throw_of_strips", "strips_lazy", "error_stats", "event_exclusion_polygons", "write_geojson", "expected_coregistration"]


class Fault:
    """A straight fault trace in a projected CRS (metres).

    Parameters
    ----------
    point : (float, float)
        A point of the trace, CRS x/y.
    strike : (float, float)
        Direction of the trace (normalised here); the right-hand normal
        ``(sy, -sx)`` points to the "right" block.
    """

    def __init__(self, point, strike):
        self.point = np.asarray(point, np.float64)
        s = np.asarray(strike, np.float64)
        self.strike = s / np.hypot(*s)
        self.normal = np.array([self.strike[1], -self.strike[0]])

    def signed_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Metres from the trace, positive on the right block, for cell
        centres ``x`` (columns) by ``y`` (rows)."""
        x = np.asarray(x, np.float64)[None, :]
        y = np.asarray(y, np.float64)[:, None]
        return (x - self.point[0]) * self.normal[0] + (y - self.point[1]) * self.normal[1]

    def to_dict(self) -> dict:
        return {"point": self.point.tolist(), "strike": self.strike.tolist(), "normal_right": self.normal.tolist()}


def strip_values(dh: np.ndarray, distance: np.ndarray, strip: tuple[float, float],
                 valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Valid ``dh`` values (float64) of the right and of the left strip
    (``strip[0] <= |distance| <= strip[1]`` metres; see :func:`throw_across`)."""
    ok = np.isfinite(dh) if valid is None else (np.asarray(valid, bool) & np.isfinite(dh))
    a = np.abs(distance)
    band = ok & (a >= strip[0]) & (a <= strip[1])
    return (np.asarray(dh[band & (distance > 0)], np.float64), np.asarray(dh[band & (distance < 0)], np.float64))


def throw_of_strips(right: np.ndarray, left: np.ndarray, strip: tuple[float, float]) -> dict:
    """:func:`throw_across` from the strips' values (:func:`strip_values`)."""
    if not right.size or not left.size:
        raise TiledsmError(
            f"throw: no valid dh in the strips {strip[0]}-{strip[1]} m on the "
            f"{'right' if not right.size else 'left'} of the fault trace (does the trace cross the grid?)"
        )
    r, l_ = float(np.median(right)), float(np.median(left))
    return {"throw": r - l_, "right": r, "left": l_, "n_right": int(right.size), "n_left": int(left.size)}


def throw_across(dh: np.ndarray, distance: np.ndarray, strip: tuple[float, float], valid: np.ndarray | None = None) -> dict:
    """Robust vertical offset across a fault trace.

    Parameters
    ----------
    dh : ndarray
        Height change, metres (NaN = none).
    distance : ndarray
        Signed distance of each cell to the trace, metres (positive: right).
    strip : (float, float)
        Inner and outer distance of the two strips, metres.
    valid : ndarray of bool, optional
        Cells allowed (e.g. visible ground).

    Returns
    -------
    dict
        ``throw`` (median right minus median left, metres), ``right``,
        ``left`` (the medians) and ``n_right``, ``n_left`` (cells used).
    """
    return throw_of_strips(*strip_values(dh, distance, strip, valid), strip)


def _block_strips(dh, valid, x, y, fault: "Fault", strip):
    return strip_values(dh, fault.signed_distance(x, y), strip, valid)


def strips_lazy(dh, fault: Fault, strip: tuple[float, float], valid=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`strip_values` of a dask-backed ``(y, x)`` DataArray, block by
    block: each task computes its cells' signed distances and returns the
    few values in its strips, so the client holds the strips' cells only
    (a scene's length times the strips' width), never the grid.

    ``valid``: a dask array of bool with the chunks of ``dh``, or None.
    """
    import dask

    data = dh.data
    x, y = np.asarray(dh.x.values, np.float64), np.asarray(dh.y.values, np.float64)
    r_edges, c_edges = np.cumsum((0,) + data.chunks[0]), np.cumsum((0,) + data.chunks[1])
    blocks = data.to_delayed()
    keep = valid.to_delayed() if valid is not None else None
    parts = []
    for i in range(blocks.shape[0]):
        for j in range(blocks.shape[1]):
            if not (np.abs(fault.signed_distance(x[c_edges[j]:c_edges[j + 1]][[0, -1]],
                                                  y[r_edges[i]:r_edges[i + 1]][[0, -1]])).min() <= strip[1]
                    or _crosses(fault, x[c_edges[j]:c_edges[j + 1]], y[r_edges[i]:r_edges[i + 1]])):
                continue  # the whole block lies beyond the outer strip
            parts.append(dask.delayed(_block_strips)(blocks[i, j], None if keep is None else keep[i, j],
                                                     x[c_edges[j]:c_edges[j + 1]], y[r_edges[i]:r_edges[i + 1]],
                                                     fault, strip))
    found = dask.compute(*parts)
    right = np.concatenate([f[0] for f in found]) if found else np.empty(0)
    left = np.concatenate([f[1] for f in found]) if found else np.empty(0)
    return right, left


def _crosses(fault: Fault, x: np.ndarray, y: np.ndarray) -> bool:
    """Whether the trace passes between a block's corner cells (signed
    distances of both signs)."""
    d = fault.signed_distance(x[[0, -1]], y[[0, -1]])
    return bool(d.min() <= 0 <= d.max())


def error_stats(err: np.ndarray) -> dict:
    """RMSE, mean, median, NMAD and 95th percentile of ``|err|`` (metres)."""
    err = np.asarray(err, np.float64)
    if err.size == 0:
        return {"count": 0}
    med = float(np.median(err))
    return {
        "count": int(err.size),
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mean": float(np.mean(err)),
        "median": med,
        "nmad": float(1.4826 * np.median(np.abs(err - med))),
        "le95": float(np.percentile(np.abs(err), 95)),
    }


def _polygon_feature(ring, name: str) -> dict:
    return {"type": "Feature", "properties": {"name": name},
            "geometry": {"type": "Polygon", "coordinates": [[[float(x), float(y)] for x, y in ring]]}}


def event_exclusion_polygons(event, origin, extent: float, uplift_tol: float = 0.05) -> tuple[list[dict], int]:
    """Exclusion polygons (GeoJSON features, scene CRS) for a synthetic event.

    Excluded: a fault-zone strip (half width ``max(10 m, 5 % of extent)``),
    the disk where the uplift exceeds ``uplift_tol`` metres, and the whole
    block holding the uplift centre — so the stable terrain left is the
    other block, which moved rigidly. With ``event.still == "left"`` the
    excluded block is the right one (it holds all the motion): the stable
    terrain is the still block.

    Returns
    -------
    features, kept_side
        ``kept_side`` is +1 when the right block is kept, -1 for the left.
    """
    p = np.asarray(event.fault_point, float) + np.asarray(origin, float)
    s, n = event.strike, event.normal
    big = 2.0 * extent  # reaches past the scene from any point of it
    half = max(10.0, 0.05 * extent)
    feats = [_polygon_feature([p - big * s - half * n, p + big * s - half * n, p + big * s + half * n,
                               p - big * s + half * n, p - big * s - half * n], "fault zone")]
    uc = np.asarray(event.uplift_center, float)
    side_uplift = 1 if float(np.dot(uc - np.asarray(event.fault_point, float), n)) >= 0 else -1
    if getattr(event, "still", "none") == "left":
        side_uplift = 1  # the moving block, whatever the uplift's place
    kept = -side_uplift
    if abs(event.uplift) > uplift_tol and getattr(event, "still", "none") != "left":
        r = event.uplift_sigma * math.sqrt(2.0 * math.log(abs(event.uplift) / uplift_tol))
        c = uc + np.asarray(origin, float)
        t = np.linspace(0.0, 2 * math.pi, 65)
        feats.append(_polygon_feature(np.column_stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)]), "uplift"))
    m = side_uplift * n
    feats.append(_polygon_feature([p - big * s, p + big * s, p + big * s + big * m, p - big * s + big * m, p - big * s],
                                  "block holding the uplift"))
    return feats, kept


def write_geojson(features: list[dict], crs: str, path: Path) -> Path:
    from tiledsm.io import atomic_path

    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": crs}}, "features": features}
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=1))
    return path


def expected_coregistration(stable: np.ndarray, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, res: float) -> dict:
    """The co-registration that would align the post surface on the stable
    cells, from the truth displacement (see the module notes).

    ``dx, dy`` metres east/north, ``dz`` metres; ``res`` metres per cell of
    a north-up grid. Returns ``dx_px, dy_px, dz`` in the signs of
    :class:`tiledsm.compare.Coregistration` (correction applied to post).
    """
    if not stable.any():
        return {"dx_px": 0.0, "dy_px": 0.0, "dz": 0.0, "n_cells": 0}
    return {
        "dx_px": -float(np.median(dx[stable])) / res,
        "dy_px": float(np.median(dy[stable])) / res,
        "dz": -float(np.median(dz[stable])),
        "n_cells": int(stable.sum()),
    }
