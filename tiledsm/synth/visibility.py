"""Per-view visibility truth on a ground grid.

A truth-grid cell is **visible** in a view when

1. its surface point ``P = (x, y, H)`` (cell centre, truth height ``H``)
   projects inside the image: ``0 <= row < rows`` and ``0 <= col < cols``
   (GDAL pixel convention, edges at integers), and
2. the line of sight through ``P`` meets no surface between ``P`` and the
   sensor farther than ``tol`` (metres, measured along the ray) from ``P``.

Condition 2 is "the first hit of the pixel's line of sight lies within
``tol`` of ``P``", the renderer's own notion of what a pixel sees: the ray is
marched **up** from ``P`` towards the sensor through the very surface the
renderer intersects (:func:`tiledsm.synth.render.surface_lattice`: the world
sampled on the absolute lattice ``i * gsd / oversample``, bilinear between
samples), in steps of half a lattice step horizontally, skipping empty space
with the renderer's 3 x 3-dilated coarse maxima, and stopping once the ray is
above the highest sample. The march from ``P`` depends only on ``P`` and the
absolute lattice, so the result does not depend on the tiling.

A cell is an **edge** cell when the height range (max - min) of the truth
surface over its 3 x 3 neighbourhood of cell centres exceeds
``edge_range`` metres (walls, roof and crown borders, where a 2.5-D DSM
cannot be evaluated fairly). The neighbourhood of a border cell uses the
truth surface beyond the grid (the world is defined everywhere).

Conventions: heights in metres above the WGS84 ellipsoid; grid cells as in
:class:`~tiledsm.geometry.grid.GroundGrid` (centre of ``[i, j]`` at
``(x0 + (j + 0.5) res, y0 - (i + 0.5) res)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from tiledsm.synth.render import COARSE, RadiometryParams, bilinear_at, coarse_max

__all__ = ["VisibilityParams", "visibility_window", "edge_cells"]


@dataclass(frozen=True)
class VisibilityParams:
    """Thresholds of the visibility truth.

    Attributes
    ----------
    tol_gsd : float
        Tolerance along the line of sight, in GSDs: a surface crossed within
        ``tol_gsd * gsd`` metres of the cell's point does not hide it.
    edge_range : float
        A cell whose 3 x 3 neighbourhood spans more than this height range
        (metres) is an edge cell.
    """

    tol_gsd: float = 1.0
    edge_range: float = 1.5

    def __post_init__(self):
        from tiledsm.errors import TiledsmError

        if not (self.tol_gsd >= 0 and self.edge_range > 0):
            raise TiledsmError(f"VisibilityParams: need tol_gsd >= 0 and edge_range > 0, got {self}")


@numba.njit(nogil=True, cache=True)
def _march_up(px, py, pz, gx, gy, u0, height, x0, y0, step, cmax, cs, zmax, out):
    """``out[k] = 1`` when the ray ``(px + u gx, py + u gy, pz + u)``,
    ``u >= u0``, stays above the bilinear surface ``height`` (sample
    ``[i, j]`` at ``(x0 + j step, y0 + i step)``) up to ``zmax``."""
    cny, cnx = cmax.shape
    for k in range(px.shape[0]):
        g = math.sqrt(gx[k] * gx[k] + gy[k] * gy[k])
        du = 0.5 * step / g if g > 0 else 1e30
        vis = 1
        n = 0
        while True:
            u = u0[k] + n * du
            z = pz[k] + u
            if z > zmax:
                break
            fx = (px[k] + u * gx[k] - x0) / step
            fy = (py[k] + u * gy[k] - y0) / step
            ci = min(max(int(math.floor(fy / cs)), 0), cny - 1)
            cj = min(max(int(math.floor(fx / cs)), 0), cnx - 1)
            if z > cmax[ci, cj]:
                # every sample within cs lattice steps horizontally is below z
                n += 2 * cs
                continue
            if bilinear_at(height, fy, fx) > z:
                vis = 0
                break
            n += 1
        out[k] = vis


def edge_cells(h_halo: np.ndarray, edge_range: float) -> np.ndarray:
    """Edge cells of a height block given with a 1-cell halo.

    Parameters
    ----------
    h_halo : (ny + 2, nx + 2) array
        Heights, metres, with one cell of halo on every side.
    edge_range : float
        Threshold on the 3 x 3 height range, metres.

    Returns
    -------
    numpy.ndarray
        bool, shape ``(ny, nx)``.
    """
    from scipy import ndimage

    h = np.asarray(h_halo, np.float32)
    rng = ndimage.maximum_filter(h, 3) - ndimage.minimum_filter(h, 3)
    return rng[1:-1, 1:-1] > edge_range


def visibility_window(
    ground,
    cameras,
    origin: tuple[float, float],
    h_range: tuple[float, float],
    grid,
    rows: tuple[int, int],
    cols: tuple[int, int],
    params: VisibilityParams = VisibilityParams(),
    radiometry: RadiometryParams = RadiometryParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Visibility and edge truth of grid cells ``rows[0]:rows[1]``,
    ``cols[0]:cols[1]`` (see module docstring).

    Parameters
    ----------
    ground : World or PostEventWorld
        The surface (``evaluate(x, y)`` on separable local grids).
    cameras : sequence of PushbroomCamera
        The views, in the world's CRS.
    origin : (float, float)
        Easting and northing of the world's local origin, metres.
    h_range : (float, float)
        Guaranteed bounds of the surface height, metres.
    grid : GroundGrid
        The truth grid (only ``x0``, ``y0``, ``resolution`` are used).
    rows, cols : (int, int)
        Half-open cell index ranges.
    params : VisibilityParams
    radiometry : RadiometryParams
        Only ``oversample`` matters: the lattice step is
        ``camera.gsd / oversample``, the renderer's.

    Returns
    -------
    visible : numpy.ndarray
        bool, ``(len(cameras), ny, nx)``.
    edge : numpy.ndarray
        bool, ``(ny, nx)``.
    """
    r0, r1 = rows
    c0, c1 = cols
    res = grid.resolution
    xs = (grid.x0 - origin[0]) + (np.arange(c0 - 1, c1 + 1) + 0.5) * res
    ys = (grid.y0 - origin[1]) - (np.arange(r0 - 1, r1 + 1) + 0.5) * res
    h_halo = ground.evaluate(xs, ys)[0]
    edge = edge_cells(h_halo, params.edge_range)
    H = h_halo[1:-1, 1:-1].astype(np.float64)
    X, Y = np.meshgrid(xs[1:-1], ys[1:-1])
    px, py, pz = X.ravel(), Y.ravel(), H.ravel()
    # per view: pixel of each point and the horizontal run of its ray per metre of rise
    rays = []
    for cam in cameras:
        row, col = cam.project_xy(px + origin[0], py + origin[1], pz)
        _, d = cam.rays(np.full_like(col, 0.5 * cam.rows), col)
        gx, gy = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]  # d points down: -d[:, 2] > 0; rising u moves by (gx, gy)
        inside = (row >= 0) & (row < cam.rows) & (col >= 0) & (col < cam.cols)
        rays.append((gx, gy, inside, cam.gsd))

    def reach(ztop):
        # rectangle the rays cross from their cell up to height ztop (segments: the end points bound it)
        xmin, xmax, ymin, ymax = px.min(), px.max(), py.min(), py.max()
        for gx, gy, _, _ in rays:
            ex, ey = px + (ztop - pz) * gx, py + (ztop - pz) * gy
            xmin, xmax = min(xmin, ex.min()), max(xmax, ex.max())
            ymin, ymax = min(ymin, ey.min()), max(ymax, ey.max())
        return xmin, xmax, ymin, ymax

    # the scene-wide bound, tightened to the surface the rays can reach (nothing above it can hide a cell,
    # and the rays stay in the first rectangle up to it): small tiles stay cheap
    ztop = min(float(h_range[1]), float(ground.height_bounds(*reach(float(h_range[1])))[1]))
    xmin, xmax, ymin, ymax = reach(max(ztop, float(pz.max())))
    step = cameras[0].gsd / radiometry.oversample
    pad = 2.0 * step
    j0, j1 = int(math.floor((xmin - pad) / step)), int(math.ceil((xmax + pad) / step))
    i0, i1 = int(math.floor((ymin - pad) / step)), int(math.ceil((ymax + pad) / step))
    lat = ground.evaluate(np.arange(j0, j1 + 1) * step, np.arange(i0, i1 + 1) * step)[0]
    lat = np.ascontiguousarray(lat, np.float32)
    cmax = coarse_max(lat, COARSE)
    zmax = float(lat.max())
    vis = np.zeros((len(cameras), r1 - r0, c1 - c0), bool)
    for v, (gx, gy, inside, gsd) in enumerate(rays):
        tol = params.tol_gsd * gsd
        u0 = tol / np.sqrt(1.0 + gx * gx + gy * gy)  # rise after tol metres along the ray
        out = np.zeros(px.size, np.uint8)
        sel = np.flatnonzero(inside)
        if sel.size:
            o = np.zeros(sel.size, np.uint8)
            _march_up(px[sel], py[sel], pz[sel], gx[sel], gy[sel], u0[sel], lat, j0 * step, i0 * step, step,
                      cmax, COARSE, zmax, o)
            out[sel] = o
        vis[v] = out.reshape(H.shape).astype(bool)
    return vis, edge
