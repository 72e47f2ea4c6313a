"""Footprints: which part of an image sees a ground tile, and which ground an
image sees. This is what makes tiling RPC-aware.

Conventions
-----------
- Image coordinates are GDAL's (see :mod:`tiledsm.geometry.rpc`): the
  top-left image corner is ``(row, col) = (0, 0)`` and array element
  ``[i, j]`` covers ``[i, i+1) x [j, j+1)``, centre ``(i+.5, j+.5)``.
- Windows are half-open integer array windows ``(row0, row1, col0, col1)``:
  ``image[row0:row1, col0:col1]``.
- Ground polygons are ``(N, 2)`` arrays of ``(lon, lat)`` degrees (WGS84),
  not closed (first vertex not repeated); heights are ellipsoidal metres.
"""

from __future__ import annotations

import math
import threading
from typing import TYPE_CHECKING

import numpy as np
from pyproj import Transformer
from scipy.spatial import ConvexHull

from tiledsm.errors import GridError, NoOverlapError
from tiledsm.geometry.grid import DEFAULT_CHUNK, GroundGrid, check_height_range, utm_crs

if TYPE_CHECKING:  # pragma: no cover
    from tiledsm.geometry.rpc import RPC

__all__ = [
    "image_window",
    "ground_polygon",
    "overlap_lonlat_bounds",
    "overlap_polygon",
    "polygon_area",
    "to_lonlat",
    "grid_for_footprint",
]

_local = threading.local()


def to_lonlat(crs: str, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Transform projected ``(x, y)`` in ``crs`` to WGS84 ``(lon, lat)``
    degrees (one cached pyproj transformer per CRS and thread)."""
    cache = getattr(_local, "transformers", None)
    if cache is None:
        cache = _local.transformers = {}
    tr = cache.get(crs)
    if tr is None:
        tr = cache[crs] = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(np.asarray(x, float), np.asarray(y, float))
    return np.asarray(lon), np.asarray(lat)


def _rect_boundary(r0: float, r1: float, c0: float, c1: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Densified rectangle boundary, ``n`` segments per side, clockwise in
    (col right, row down) space, starting at ``(r0, c0)``, not closed."""
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    rows = np.concatenate([np.full(n, r0), r0 + t * (r1 - r0), np.full(n, r1), r1 - t * (r1 - r0)])
    cols = np.concatenate([c0 + t * (c1 - c0), np.full(n, c1), c1 - t * (c1 - c0), np.full(n, c0)])
    return rows, cols


def image_window(
    rpc: "RPC",
    grid: "GroundGrid",
    h_range: tuple[float, float],
    image_shape: tuple[int, int] | None = None,
    margin: int = 2,
    n_per_side: int = 16,
) -> tuple[int, int, int, int] | None:
    """Image window that sees a ground tile over a height range.

    The tile's outer boundary (cell edges, densified with ``n_per_side``
    points per side) is converted to lon/lat and projected through the RPC
    at the lowest, middle and highest height; the window is the smallest
    set of whole pixels containing all projected points, grown by
    ``margin`` pixels on every side, then clipped to the image.

    Parameters
    ----------
    rpc : RPC
        Image camera.
    grid : GroundGrid
        The ground tile (any projected CRS).
    h_range : (hmin, hmax)
        Ellipsoidal heights, metres.
    image_shape : (rows, cols), optional
        Image size; when given the window is clipped to it and ``None`` is
        returned when the tile is not seen at all. When omitted the window
        is returned unclipped (may extend outside the image).
    margin : int
        Extra pixels on each side (interpolation support, matching windows).
    n_per_side : int
        Boundary points per tile side.

    Returns
    -------
    (row0, row1, col0, col1) or None
        Half-open array window.

    Notes
    -----
    Visibility is decided before the margin is added: a tile whose
    projection misses the image is ``None`` even if its margin would touch it.
    """
    hmin, hmax = check_height_range(h_range)
    left, bottom, right, top = grid.bounds
    ys, xs = _rect_boundary(top, bottom, left, right, max(int(n_per_side), 1))
    lon, lat = to_lonlat(grid.crs, xs, ys)
    hs = np.array([hmin, 0.5 * (hmin + hmax), hmax])[:, None]
    rows, cols = rpc.project(lon[None, :], lat[None, :], hs)
    if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(cols))):
        raise GridError(f"image_window: tile {grid.bounds} projects to non-finite pixels through {rpc.source or 'RPC'}")
    r0 = math.floor(rows.min())
    r1 = math.floor(rows.max()) + 1
    c0 = math.floor(cols.min())
    c1 = math.floor(cols.max()) + 1
    m = int(margin)
    if image_shape is None:
        return (r0 - m, r1 + m, c0 - m, c1 + m)
    nr, nc = int(image_shape[0]), int(image_shape[1])
    if r1 <= 0 or c1 <= 0 or r0 >= nr or c0 >= nc:
        return None
    return (max(r0 - m, 0), min(r1 + m, nr), max(c0 - m, 0), min(c1 + m, nc))


def ground_polygon(rpc: "RPC", image_shape: tuple[int, int], h: float, n_per_side: int = 16) -> np.ndarray:
    """Ground footprint of a whole image at one height.

    Parameters
    ----------
    rpc : RPC
        Image camera.
    image_shape : (rows, cols)
        Image size; the boundary follows the outer pixel edges
        (rows 0 and ``rows``, columns 0 and ``cols``, GDAL convention).
    h : float
        Ellipsoidal height, metres.
    n_per_side : int
        Points per image side.

    Returns
    -------
    numpy.ndarray
        ``(4 * n_per_side, 2)`` ``(lon, lat)`` degrees, in image-boundary
        order (top edge left to right, then right edge, bottom, left).
    """
    nr, nc = int(image_shape[0]), int(image_shape[1])
    if nr <= 0 or nc <= 0:
        raise GridError(f"ground_polygon: empty image shape {tuple(image_shape)}")
    rows, cols = _rect_boundary(0.0, nr, 0.0, nc, max(int(n_per_side), 1))
    lon, lat = rpc.localize(rows, cols, np.full(rows.shape, float(h)))
    return np.column_stack([lon, lat])


def _bbox(poly: np.ndarray) -> tuple[float, float, float, float]:
    return (poly[:, 0].min(), poly[:, 1].min(), poly[:, 0].max(), poly[:, 1].max())


def overlap_lonlat_bounds(
    rpc1: "RPC",
    shape1: tuple[int, int],
    rpc2: "RPC",
    shape2: tuple[int, int],
    h_range: tuple[float, float],
) -> tuple[float, float, float, float]:
    """Lon/lat box seen by both images somewhere in a height range.

    Each image's footprint is the bounding box of its ground polygons at
    ``hmin`` and ``hmax``; the result is the intersection of the two boxes.

    Returns
    -------
    (lon_min, lat_min, lon_max, lat_max)
        Degrees.

    Raises
    ------
    NoOverlapError
        The boxes are disjoint.
    """
    hmin, hmax = check_height_range(h_range)
    b = []
    for rpc, shape in ((rpc1, shape1), (rpc2, shape2)):
        poly = np.concatenate([ground_polygon(rpc, shape, h) for h in (hmin, hmax)])
        b.append(tuple(float(v) for v in _bbox(poly)))
    lo0, la0 = max(b[0][0], b[1][0]), max(b[0][1], b[1][1])
    lo1, la1 = min(b[0][2], b[1][2]), min(b[0][3], b[1][3])
    if lo0 >= lo1 or la0 >= la1:
        names = " and ".join(r.source or f"image {k + 1}" for k, r in enumerate((rpc1, rpc2)))
        raise NoOverlapError(
            f"{names} see no common ground for heights {hmin}..{hmax} m "
            f"(lon/lat boxes {_fmt(b[0])} / {_fmt(b[1])})"
        )
    return (float(lo0), float(la0), float(lo1), float(la1))


def _fmt(box) -> str:
    return "(" + ", ".join(f"{v:.6f}" for v in box) + ")"


def polygon_area(poly: np.ndarray) -> float:
    """Signed shoelace area of a ``(N, 2)`` polygon (positive when
    counter-clockwise in x-right, y-up axes), in squared input units."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: ``subject`` clipped by convex counter-clockwise ``clip``."""
    out = subject
    n = len(clip)
    for k in range(n):
        if len(out) == 0:
            break
        a, b = clip[k], clip[(k + 1) % n]
        edge = b - a
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])  # >= 0: inside (left)
        prev = np.roll(out, 1, axis=0)
        prev_side = np.roll(side, 1)
        pts = []
        for p, q, sp, sq in zip(prev, out, prev_side, side):
            if sq >= 0:
                if sp < 0:
                    pts.append(p + (q - p) * (sp / (sp - sq)))
                pts.append(q)
            elif sp >= 0:
                pts.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(pts).reshape(-1, 2)
    return out


def overlap_polygon(
    rpc1: "RPC",
    shape1: tuple[int, int],
    rpc2: "RPC",
    shape2: tuple[int, int],
    h: float,
    n_per_side: int = 16,
) -> np.ndarray:
    """Ground polygon seen by both images at one height.

    Intersection of the first :func:`ground_polygon` footprint with the
    convex hull of the second, by Sutherland-Hodgman clipping. Satellite
    footprints on a constant-height surface are convex up to the RPC's
    curvature (a relative area of ~1e-5 on a Pleiades crop), so the hull
    changes the result by less than that.

    Returns
    -------
    numpy.ndarray
        ``(N, 2)`` ``(lon, lat)`` degrees, counter-clockwise.

    Raises
    ------
    NoOverlapError
        The footprints are disjoint.
    """
    p1 = ground_polygon(rpc1, shape1, h, n_per_side)
    p2 = ground_polygon(rpc2, shape2, h, n_per_side)
    if polygon_area(p1) < 0:
        p1 = p1[::-1]
    p2 = p2[ConvexHull(p2).vertices]  # counter-clockwise
    out = _clip_convex(p1, p2)
    if len(out) < 3 or abs(polygon_area(out)) == 0:
        names = " and ".join(r.source or f"image {k + 1}" for k, r in enumerate((rpc1, rpc2)))
        raise NoOverlapError(f"{names} see no common ground at height {h} m")
    return out


def grid_for_footprint(
    rpc,
    image_shape: tuple[int, int],
    h_range: tuple[float, float],
    resolution: float,
    crs: str | None = None,
    chunk: int = DEFAULT_CHUNK,
) -> GroundGrid:
    """A ground grid covering everything an image can see in a height range.

    The image boundary is localised at the lowest and highest height; the
    grid is the bounding box of those polygons in ``crs`` snapped outward
    (:meth:`GroundGrid.from_bounds`).

    Parameters
    ----------
    rpc : RPC
        Camera of the image.
    image_shape : (rows, cols)
        Image size, pixels.
    h_range : (hmin, hmax)
        Ellipsoidal heights, metres.
    resolution : float
        Cell edge, metres.
    crs : str, optional
        Output CRS; default the UTM zone of the footprint centre.
    chunk : int
        Chunk edge, cells.
    """
    from pyproj import Transformer

    hmin, hmax = check_height_range(h_range)
    polys = np.concatenate([ground_polygon(rpc, image_shape, h) for h in (hmin, hmax)])
    if crs is None:
        lon_c = 0.5 * (polys[:, 0].min() + polys[:, 0].max())
        lat_c = 0.5 * (polys[:, 1].min() + polys[:, 1].max())
        crs = utm_crs(lon_c, lat_c)
    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x, y = tr.transform(polys[:, 0], polys[:, 1])
    return GroundGrid.from_bounds(crs, (x.min(), y.min(), x.max(), y.max()), resolution, chunk)
