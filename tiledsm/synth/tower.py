"""One tall, narrow tower with a flat roof, placed on the truth grid.

A test object for DSM stages: a square footprint, axis-aligned on the
truth grid with its sides on cell edges (so the truth cells on the roof are
exactly a ``window`` of the grid), vertical walls and a flat roof at

    ``roof_height = max(bare ground over the footprint) + height_m``

(metres above the WGS84 ellipsoid; the bare ground is the relief, sampled
every ``gsd / 4`` over the closed footprint). The roof is textured like the
buildings' roofs: albedo ``roof_albedo * (1 + 0.3 T(x, y))`` with the
world's unit-variance texture ``T``, so it can be matched. Its label is
1 (building). Optionally, buildings and trees within ``clearance_m`` of the
footprint are removed (bare, textured ground around the tower).

The tower is part of the :class:`~tiledsm.synth.terrain.World`
(``World.tower``): its ``evaluate`` and ``height_bounds`` include it, so the
truth rasters, the occlusion-aware renderer and the visibility truth all see
the same tower (walls hide the ground behind them, the roof is seen by every
view whose footprint holds it).

Conventions: local coordinates are metres east/north of the scene origin;
a footprint point ``(x, y)`` is on the tower when ``x0 <= x <= x1`` and
``y0 <= y <= y1`` (closed square).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tiledsm.synth.texture import TextureParams, ground_albedo

__all__ = ["TowerParams", "Tower", "place_tower", "apply_tower"]


@dataclass(frozen=True)
class TowerParams:
    """What tower to place (lengths in metres).

    Attributes
    ----------
    height_m : float
        Roof height above the highest bare ground under the footprint, > 0.
    side_m : float
        Footprint side; rounded to a whole number of truth cells (>= 1).
    offset_m : (float, float)
        Footprint centre, metres east and north of the scene centre; the
        footprint is snapped to the nearest cell edges of the truth grid.
    roof_albedo : float
        Mean roof albedo, in (0, 1] (texture modulates it by 30 %).
    clearance_m : float
        Buildings and trees are removed within this distance (metres,
        per axis: a square ring) of the footprint; 0 keeps them (the tower
        then overrides whatever its footprint covers).
    """

    height_m: float = 65.0
    side_m: float = 16.0
    offset_m: tuple[float, float] = (0.0, 0.0)
    roof_albedo: float = 0.55
    clearance_m: float = 0.0

    def __post_init__(self) -> None:
        from tiledsm.errors import TiledsmError

        ok = (self.height_m > 0 and self.side_m > 0 and 0 < self.roof_albedo <= 1 and self.clearance_m >= 0
              and all(math.isfinite(v) for v in (self.height_m, self.side_m, *self.offset_m, self.clearance_m)))
        if not ok:
            raise TiledsmError(f"TowerParams: need height_m > 0, side_m > 0, roof_albedo in (0, 1], "
                               f"clearance_m >= 0, finite values; got {self}")


@dataclass(frozen=True)
class Tower:
    """A tower placed on a truth grid (build it with :func:`place_tower`).

    Attributes
    ----------
    params : TowerParams
        What was asked.
    window : (int, int, int, int)
        ``(row0, row1, col0, col1)``: the half-open truth-grid cell ranges
        whose centres are on the roof (the footprint exactly).
    footprint : (float, float, float, float)
        ``(x0, x1, y0, y1)``: the footprint's edges, local metres (east,
        north of the world origin).
    roof_height : float
        Roof height, metres above the WGS84 ellipsoid (a float32 value: the
        truth DSM holds it exactly).
    ground_max : float
        Highest bare ground under the footprint, metres (ellipsoidal).
    """

    params: TowerParams
    window: tuple[int, int, int, int]
    footprint: tuple[float, float, float, float]
    roof_height: float
    ground_max: float

    @property
    def cleared(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of the footprint grown by ``clearance_m``, local metres."""
        c = self.params.clearance_m
        x0, x1, y0, y1 = self.footprint
        return x0 - c, x1 + c, y0 - c, y1 + c

    def intersects(self, xmin: float, xmax: float, ymin: float, ymax: float) -> bool:
        """Whether the footprint meets the rectangle (local metres)."""
        x0, x1, y0, y1 = self.footprint
        return x0 <= xmax and xmin <= x1 and y0 <= ymax and ymin <= y1

    def to_dict(self, grid, origin: tuple[float, float]) -> dict:
        """JSON-ready description: window, roof height and footprint in the grid's CRS."""
        from dataclasses import asdict

        x0, x1, y0, y1 = self.footprint
        return {
            "params": asdict(self.params),
            "window_rows_cols": list(self.window),
            "footprint_ltrb": [x0 + origin[0], y0 + origin[1], x1 + origin[0], y1 + origin[1]],
            "roof_height_m": self.roof_height,
            "ground_max_m": self.ground_max,
            "definition": "roof flat at roof_height_m over the closed footprint (vertical walls); truth cells "
            "window_rows_cols = (row0, row1, col0, col1), half-open; roof_height_m = ground_max_m + height_m",
        }


def _snap(centre: float, side_cells: int, edge0: float, res: float, sign: int) -> int:
    """First cell index of a ``side_cells`` run centred near ``centre`` on a
    grid whose cell ``k`` starts at ``edge0 + sign * k * res``."""
    return int(round(sign * (centre - edge0) / res - 0.5 * side_cells))


def place_tower(world, params: TowerParams, grid, origin: tuple[float, float]) -> Tower:
    """Snap a tower to the truth grid and fix its roof height.

    Parameters
    ----------
    world : World
        The world it stands in (its relief gives the ground under it).
    params : TowerParams
    grid : GroundGrid
        The truth grid; the footprint's sides fall on its cell edges.
    origin : (float, float)
        Easting and northing of the world's local origin, metres.

    Returns
    -------
    Tower

    Raises
    ------
    TiledsmError
        The footprint (plus one cell) does not fit in the grid.
    """
    from tiledsm.errors import TiledsmError

    res = float(grid.resolution)
    n = max(1, int(round(params.side_m / res)))
    gx0 = grid.x0 - origin[0]  # west edge of column 0, local metres
    gy0 = grid.y0 - origin[1]  # north edge of row 0
    cx = gx0 + 0.5 * grid.width * res + params.offset_m[0]
    cy = gy0 - 0.5 * grid.height * res + params.offset_m[1]
    col0 = _snap(cx, n, gx0, res, 1)
    row0 = _snap(cy, n, gy0, res, -1)
    if not (1 <= row0 and row0 + n <= grid.height - 1 and 1 <= col0 and col0 + n <= grid.width - 1):
        raise TiledsmError(f"place_tower: a {n}-cell footprint at offset {params.offset_m} m does not fit "
                           f"inside the {grid.height} x {grid.width} truth grid")
    x0, x1 = gx0 + col0 * res, gx0 + (col0 + n) * res
    y0, y1 = gy0 - (row0 + n) * res, gy0 - row0 * res
    m = int(math.ceil(4 * n)) + 1  # samples every gsd / 4, edges included
    ground = world.relief.grid(np.linspace(x0, x1, m), np.linspace(y0, y1, m), dtype=np.float64)
    ground_max = float(ground.max()) + float(world.terrain.base_height)
    roof = float(np.float32(ground_max + params.height_m))
    return Tower(params, (row0, row0 + n, col0, col0 + n), (x0, x1, y0, y1), roof, ground_max)


def _span(v: np.ndarray, lo: float, hi: float) -> slice:
    """Indices of the sorted-or-reversed 1-D ``v`` inside ``[lo, hi]``, as a slice."""
    idx = np.flatnonzero((v >= lo) & (v <= hi))
    return slice(int(idx[0]), int(idx[-1]) + 1) if idx.size else slice(0, 0)


def apply_tower(tower: Tower, x: np.ndarray, y: np.ndarray, height: np.ndarray, albedo: np.ndarray,
                label: np.ndarray, tex: np.ndarray, bare: np.ndarray | None, texture: TextureParams) -> None:
    """Draw the tower into a world's separable-grid evaluation, in place.

    Parameters
    ----------
    tower : Tower
    x, y : numpy.ndarray
        1-D local coordinates (monotonic), metres; element ``[i, j]`` of the
        arrays is at ``(x[j], y[i])``.
    height, albedo, label : numpy.ndarray
        The evaluation (metres ellipsoidal, [0, 1], class), modified.
    tex : numpy.ndarray
        The unit-variance texture on the same grid.
    bare : numpy.ndarray or None
        The bare-ground heights (relief only) on the same grid, metres;
        needed when ``tower.params.clearance_m > 0``.
    texture : TextureParams
        The world's texture parameters (ground albedo of the cleared ring).
    """
    if tower.params.clearance_m > 0:
        cx0, cx1, cy0, cy1 = tower.cleared
        rs, cs = _span(y, cy0, cy1), _span(x, cx0, cx1)
        if rs.stop > rs.start and cs.stop > cs.start:
            height[rs, cs] = bare[rs, cs]
            albedo[rs, cs] = ground_albedo(tex[rs, cs], texture)
            label[rs, cs] = 0
    x0, x1, y0, y1 = tower.footprint
    rs, cs = _span(y, y0, y1), _span(x, x0, x1)
    if rs.stop > rs.start and cs.stop > cs.start:
        a = np.float32(tower.params.roof_albedo) * (np.float32(1.0) + np.float32(0.3) * tex[rs, cs])
        height[rs, cs] = np.float32(tower.roof_height)
        albedo[rs, cs] = np.clip(a, 0.02, 1.0)
        label[rs, cs] = 1
