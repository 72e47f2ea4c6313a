"""Post-event world: a known displacement field applied to the ground.

The displacement is a straight fault (a vertical plane through
``fault_point`` with strike ``strike_deg``) whose two blocks move rigidly
along the strike and vertically -- by ``+-slip/2`` and ``+-throw/2``
(``still="none"``: both blocks move, nothing is still), or the right block
by ``slip`` and ``throw`` while the left one stays (``still="left"``: the
usual real case, where far-field ground on one side is a stable frame) --
plus a smooth Gaussian uplift (vertical only; with ``still="left"`` on the
right block only, so the left block is truly still).

Convention
----------
``dx, dy, dz`` at a position ``q`` (local metres east/north) are the
displacement of the ground point that is at ``q`` *after* the event: it
was at ``q - (dx, dy)`` before and rose by ``dz``. So the post-event
surface is ``f_post(q) = f_pre(q - (dx, dy)) + dz(q)`` and the post-event
albedo moves with the ground. Because the horizontal displacement is
constant on each block, each block's post-event surface is the pre-event
world evaluated on a shifted separable grid: exact, and seamless across
tiles.

``dh = f_post - f_pre`` (the DSM difference a change-detection pipeline
measures) differs from ``dz`` on slopes and at object edges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["EventParams", "BLOCK_SHARES", "displacement", "evaluate_post"]

#: share of the slip and throw moved by the (right, left) block, per ``EventParams.still``
BLOCK_SHARES = {"none": (0.5, -0.5), "left": (1.0, 0.0)}


@dataclass(frozen=True)
class EventParams:
    """Displacement field parameters (metres, degrees; local coordinates).

    Attributes
    ----------
    fault_point : (float, float)
        A point of the fault trace, metres east/north of the scene origin.
    strike_deg : float
        Fault trace azimuth, degrees clockwise from grid north.
    throw : float
        Vertical offset between the blocks (the block right of the strike
        direction goes up by ``throw / 2``, the other down by as much).
    slip : float
        Horizontal offset along the strike between the blocks (right block
        moves ``+slip / 2`` along the strike direction).
    uplift : float
        Peak of the Gaussian uplift, metres.
    uplift_center : (float, float)
        Its centre, metres east/north of the scene origin.
    uplift_sigma : float
        Its standard deviation, metres.
    post_aim_offset : (float, float)
        Metres east/north by which the post-event cameras aim away from the
        pre-event ones (each post view gets its own RPC): the post images
        sample the ground at another sub-pixel phase, as a second orbit
        does, so still ground carries the resampling errors moving ground
        has. ``(0, 0)``: the post views share the pre views' cameras.
    post_bh : float or None
        Base-to-height ratio of the post-event pair (None: the pre pair's):
        another base changes the sub-pixel phase of every disparity, so the
        matching errors of still ground differ between the epochs, as they
        do between two real acquisitions.
    still : {"none", "left"}
        ``"none"``: the blocks move by ``+-slip/2`` and ``+-throw/2``;
        ``"left"``: the left block stays, the right one moves by ``slip``
        and ``throw`` and carries the uplift (``"none"``: the uplift is
        added on both blocks).
    """

    fault_point: tuple[float, float] = (30.0, -20.0)
    strike_deg: float = 35.0
    throw: float = 2.0
    slip: float = 1.5
    uplift: float = 1.0
    uplift_center: tuple[float, float] = (-60.0, 80.0)
    uplift_sigma: float = 120.0
    still: str = "none"
    post_aim_offset: tuple[float, float] = (0.0, 0.0)
    post_bh: float | None = None

    def __post_init__(self) -> None:
        if self.still not in BLOCK_SHARES:
            raise ValueError(f"still: expected one of {sorted(BLOCK_SHARES)}, got {self.still!r}")

    @classmethod
    def for_extent(cls, extent: float, **kw) -> "EventParams":
        """Defaults scaled to a scene ``extent`` metres wide (``kw`` overrides).

        With ``still="left"`` the uplift sits on the moving (right) block."""
        base = dict(
            fault_point=(0.06 * extent, -0.04 * extent),
            uplift_center=(-0.12 * extent, 0.16 * extent),
            uplift_sigma=0.25 * extent,
        )
        if kw.get("still") == "left":
            base.update(uplift_center=(0.22 * extent, -0.2 * extent), uplift_sigma=0.12 * extent)
        return cls(**{**base, **kw})

    @property
    def shares(self) -> tuple[float, float]:
        """Share of ``slip`` and ``throw`` moved by the (right, left) block."""
        return BLOCK_SHARES[self.still]

    @property
    def strike(self) -> np.ndarray:
        s = math.radians(self.strike_deg)
        return np.array([math.sin(s), math.cos(s)])

    @property
    def normal(self) -> np.ndarray:
        """Unit horizontal vector pointing to the "right" block."""
        sx, sy = self.strike
        return np.array([sy, -sx])

    @property
    def max_vertical(self) -> float:
        """Bound on ``|dz|``, metres."""
        return max(abs(v) for v in self.shares) * abs(self.throw) + abs(self.uplift)

    @property
    def max_horizontal(self) -> float:
        """Bound on ``|(dx, dy)|``, metres."""
        return max(abs(v) for v in self.shares) * abs(self.slip)


def displacement(event: EventParams, x: np.ndarray, y: np.ndarray):
    """Displacement on the separable grid ``x`` (columns) by ``y`` (rows).

    Returns
    -------
    side : numpy.ndarray
        bool, True on the right block.
    dx, dy, dz : numpy.ndarray
        float32, metres (see the module's convention).
    """
    x = np.asarray(x, np.float64)[None, :]
    y = np.asarray(y, np.float64)[:, None]
    nx, ny = event.normal
    side = (x - event.fault_point[0]) * nx + (y - event.fault_point[1]) * ny >= 0
    sgn = np.where(side, *event.shares)
    sx, sy = event.strike
    dx = (sgn * event.slip * sx).astype(np.float32)
    dy = (sgn * event.slip * sy).astype(np.float32)
    r2 = (x - event.uplift_center[0]) ** 2 + (y - event.uplift_center[1]) ** 2
    uplift = event.uplift * np.exp(-0.5 * r2 / event.uplift_sigma**2)
    if event.still == "left":
        uplift = np.where(side, uplift, 0.0)
    dz = sgn * event.throw + uplift
    return side, dx, dy, dz.astype(np.float32)


def evaluate_post(world, event: EventParams, x: np.ndarray, y: np.ndarray):
    """Post-event height, albedo and label on a separable grid, plus the
    displacement ``(dx, dy, dz)`` (see :func:`displacement`)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    side, dx, dy, dz = displacement(event, x, y)
    right, left = (share * event.slip * event.strike for share in event.shares)
    h_r, a_r, l_r = world.evaluate(x - right[0], y - right[1])
    h_l, a_l, l_l = world.evaluate(x - left[0], y - left[1])
    h = np.where(side, h_r, h_l) + dz
    a = np.where(side, a_r, a_l)
    lab = np.where(side, l_r, l_l)
    return h.astype(np.float32), a, lab, dx, dy, dz


@dataclass(frozen=True, eq=False)
class PostEventWorld:
    """The world after the event: same interface as
    :class:`~tiledsm.synth.terrain.World` (``evaluate``, ``height_bounds``),
    so the renderer draws it unchanged."""

    world: object
    event: EventParams

    def evaluate(self, x, y):
        """Post-event ``(height, albedo, label)`` on a separable grid."""
        return evaluate_post(self.world, self.event, x, y)[:3]

    def height_bounds(self, xmin, xmax, ymin, ymax):
        """Guaranteed post-event height bounds over a rectangle (metres)."""
        m = self.event.max_horizontal
        lo, hi = self.world.height_bounds(xmin - m, xmax + m, ymin - m, ymax + m)
        v = self.event.max_vertical
        return lo - v, hi + v
