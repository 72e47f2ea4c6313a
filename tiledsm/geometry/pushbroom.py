"""A physical pushbroom (linear-array) satellite camera.

Model
-----
The camera works in a local Cartesian frame: the easting and northing of a
projected CRS (UTM) and the height above the WGS84 ellipsoid, all metres
(a flat-Earth frame, fine over the few tens of kilometres of a scene).

- The satellite flies a straight line at ``altitude`` metres above the aim
  point's height, along the horizontal unit vector ``a`` of azimuth
  ``azimuth_deg`` (degrees clockwise from grid north; ~190 for a
  descending sun-synchronous pass).
- Each image row is acquired at its own time: row ``r`` is taken with the
  satellite at ``S(r) = S_mid + a * gsd * (r - rows / 2)`` (GDAL row
  coordinate, so the ground footprint advances one ``gsd`` per row on
  level ground; the line period is ``gsd / ground_speed`` seconds).
- The attitude is fixed during the acquisition: roll ``roll_deg`` (about the
  flight direction, positive towards the columns' direction) then pitch
  ``pitch_deg`` (along-track incidence, positive looking forward). The
  boresight is ``b``, the detector line direction ``e`` (perpendicular to
  ``b``, roughly cross-track).
- Detector ``col`` looks along ``b + xi e`` with ``xi = (col - cols / 2) * p``
  (a pinhole line camera); the pitch ``p`` is chosen so the cross-track
  ground sample distance is ``gsd`` at the image centre on level ground.
- The central pixel at mid-acquisition sees the aim point ``(e0, n0, h0)``.

Pixel convention: GDAL's, like :class:`~tiledsm.geometry.rpc.RPC` (top-left
image corner at (0, 0), centre of element ``[i, j]`` at ``(i+0.5, j+0.5)``).

The along-track parallax between two views of pitches ``t1``, ``t2`` is
``tan t1 - tan t2`` metres of horizontal shift per metre of height: the
base-to-height ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["PushbroomCamera"]


@dataclass(frozen=True)
class PushbroomCamera:
    """A pushbroom camera in a projected CRS (see module docstring).

    Parameters
    ----------
    crs : str
        Projected CRS of the local frame (e.g. ``"EPSG:32631"``).
    e0, n0, h0 : float
        Aim point of the central pixel at mid-acquisition: easting and
        northing (metres, ``crs``) and height (metres, WGS84 ellipsoid).
    rows, cols : int
        Image size, pixels.
    gsd : float
        Ground sample distance on level ground at the image centre, metres.
    pitch_deg, roll_deg : float
        Along-track incidence (forward positive) and roll, degrees.
    azimuth_deg : float
        Flight direction, degrees clockwise from grid north.
    altitude : float
        Orbit height above ``h0``, metres.
    ground_speed : float
        Ground-track speed, metres per second (only sets :attr:`line_period`).
    """

    crs: str
    e0: float
    n0: float
    h0: float
    rows: int
    cols: int
    gsd: float
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    azimuth_deg: float = 190.0
    altitude: float = 700e3
    ground_speed: float = 6800.0

    # ------------------------------------------------------------- frame
    @cached_property
    def _frame(self):
        az = math.radians(self.azimuth_deg)
        a = np.array([math.sin(az), math.cos(az), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        c = np.cross(up, a)  # right of the flight direction
        rho = math.radians(self.roll_deg)
        th = math.radians(self.pitch_deg)
        b1 = -up * math.cos(rho) + c * math.sin(rho)
        e = c * math.cos(rho) + up * math.sin(rho)
        b = b1 * math.cos(th) + a * math.sin(th)
        p0 = np.array([self.e0, self.n0, self.h0])
        s_mid = p0 - b * (self.altitude / -b[2])
        n = np.cross(b, e)
        # detector pitch: cross-track GSD = gsd at the centre on level ground
        eps = 1e-7
        d1 = b + eps * e
        d0 = b - eps * e
        g1 = s_mid + d1 * ((self.h0 - s_mid[2]) / d1[2])
        g0 = s_mid + d0 * ((self.h0 - s_mid[2]) / d0[2])
        pitch = self.gsd * 2 * eps / float(np.linalg.norm(g1[:2] - g0[:2]))
        return a, b, e, n, s_mid, pitch

    @property
    def line_period(self) -> float:
        """Time between two rows, seconds."""
        return self.gsd / self.ground_speed

    @property
    def view_vector(self) -> np.ndarray:
        """Unit boresight (east, north, up) pointing from the satellite to the ground."""
        return self._frame[1].copy()

    def parallax(self) -> np.ndarray:
        """Horizontal shift (east, north) of the boresight's ground point per
        metre of height increase, metres/metre (the view's ``tan`` incidence
        vector, pointing towards the satellite)."""
        b = self._frame[1]
        return b[:2] / b[2]

    # ------------------------------------------------------------- rays
    def rays(self, row, col) -> tuple[np.ndarray, np.ndarray]:
        """Sensor positions and unit-free look directions of image points.

        Parameters
        ----------
        row, col : array_like
            Pixel coordinates, GDAL convention; broadcast together.

        Returns
        -------
        origin, direction : numpy.ndarray
            Shape ``broadcast + (3,)``: satellite position (east, north,
            height, metres) when ``row`` was acquired, and the direction
            ``b + xi e`` of pixel ``col`` (not normalised; its height
            component is negative).
        """
        a, b, e, _, s_mid, pitch = self._frame
        row, col = np.broadcast_arrays(np.asarray(row, float), np.asarray(col, float))
        s = (row - 0.5 * self.rows) * self.gsd
        xi = (col - 0.5 * self.cols) * pitch
        origin = s_mid + s[..., None] * a
        direction = b + xi[..., None] * e
        return origin, direction

    def project_xy(self, x, y, h) -> tuple[np.ndarray, np.ndarray]:
        """Project ground points given in the local frame.

        Parameters
        ----------
        x, y : array_like
            Easting and northing in :attr:`crs`, metres.
        h : array_like
            Height above the WGS84 ellipsoid, metres.

        Returns
        -------
        row, col : numpy.ndarray
            GDAL pixel convention.
        """
        a, b, e, n, s_mid, pitch = self._frame
        x, y, h = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(h, float))
        w0 = np.stack([x - s_mid[0], y - s_mid[1], h - s_mid[2]], axis=-1)
        s = (w0 @ n) / float(n @ a)  # along-track position of the scan plane through the point
        w = w0 - s[..., None] * a
        xi = (w @ e) / (w @ b)
        row = 0.5 * self.rows + s / self.gsd
        col = 0.5 * self.cols + xi / pitch
        return row, col

    def localize_xy(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:
        """Ground position (easting, northing in :attr:`crs`, metres) of
        image points at heights ``h`` (metres, WGS84 ellipsoid)."""
        origin, direction = self.rays(row, col)
        h = np.asarray(h, float)
        lam = (h - origin[..., 2]) / direction[..., 2]
        return origin[..., 0] + lam * direction[..., 0], origin[..., 1] + lam * direction[..., 1]

    # --------------------------------------------------------- lon / lat
    @cached_property
    def _to_crs(self):
        from pyproj import Transformer

        return Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)

    @cached_property
    def _from_crs(self):
        from pyproj import Transformer

        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        """Project WGS84 ``lon``, ``lat`` (degrees) and ellipsoidal height
        ``h`` (metres) to ``(row, col)``, GDAL pixel convention."""
        lon, lat, h = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float))
        x, y = self._to_crs.transform(lon, lat)
        return self.project_xy(x, y, h)

    def localize(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`project` at heights ``h``: ``(lon, lat)`` degrees."""
        x, y = self.localize_xy(row, col, h)
        return self._from_crs.transform(x, y)
