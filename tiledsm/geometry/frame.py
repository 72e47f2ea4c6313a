"""Frame (pinhole) camera with Brown distortion and exterior orientation.

The model of UAV and aerial frame images, with the
:class:`~tiledsm.geometry.camera.Camera` interface of the RPC model.

Model
-----
A ground point ``X = (E, N, h)`` (easting and northing in the projected CRS
``crs``, metres; ``h`` ellipsoidal metres) is seen at

.. math::

    (x_c, y_c, z_c) = R (X - C), \\quad x = x_c / z_c, \\quad y = y_c / z_c

(camera axes as OpenCV's: ``x`` right, ``y`` down, ``z`` forward), then
distorted by Brown's model with OpenCV's coefficient names
(Brown 1966, Photogramm. Eng. 32(3) 444-462):

.. math::

    r^2 = x^2 + y^2, \\quad q = 1 + k_1 r^2 + k_2 r^4 + k_3 r^6

    x_d = x q + 2 p_1 x y + p_2 (r^2 + 2 x^2), \\quad
    y_d = y q + p_1 (r^2 + 2 y^2) + 2 p_2 x y

and ``col = fx x_d + cx``, ``row = fy y_d + cy``.

Conventions
-----------
- Pixel coordinates are GDAL's (top-left image corner at ``(0, 0)``, pixel
  ``[i, j]`` centred at ``(i+.5, j+.5)``), so ``cx, cy`` here are OpenCV's
  principal point **plus 0.5** (OpenCV centres pixel ``[0, 0]`` at
  ``(0, 0)``; COLMAP already uses the corner convention).
  :meth:`FrameCamera.from_opencv` converts.
- The world frame is the projected CRS plane with ellipsoidal heights as
  the third axis (a local, flat ENU frame): Earth curvature and the map
  projection's scale error are neglected. At 500 m from the camera's
  nadir the curvature drop is 2 cm; keep flights small (UAV blocks).
- Points behind the camera (``z_c <= 0``) project to NaN.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from dataclasses import dataclass, field

import numpy as np
from pyproj import Transformer

from tiledsm.errors import RPCError

__all__ = ["FrameCamera", "rotation_nadir", "rodrigues", "transformer"]

_local = threading.local()


def transformer(src: str, dst: str) -> Transformer:
    """One cached pyproj transformer per (src, dst) and thread."""
    cache = getattr(_local, "transformers", None)
    if cache is None:
        cache = _local.transformers = {}
    tr = cache.get((src, dst))
    if tr is None:
        tr = cache[(src, dst)] = Transformer.from_crs(src, dst, always_xy=True)
    return tr


def rodrigues(rvec) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle, radians),
    as ``cv2.Rodrigues``."""
    r = np.asarray(rvec, float).ravel()
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


def rotation_nadir(heading_deg: float = 0.0, roll_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """World-to-camera rotation of a (nearly) nadir-looking camera.

    With all angles zero the camera looks straight down with the image's
    top towards grid north (``x`` east, ``y`` south, ``z`` down).
    ``heading_deg`` turns the image's top clockwise from north (the flight
    direction); ``roll_deg`` tilts the view towards the image's right
    (rotation about the image ``y`` axis) and ``pitch_deg`` towards its top
    (about the image ``x`` axis), both in the camera frame.
    """
    base = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    a = math.radians(heading_deg)
    # world rotation about "up" by -heading, so the image top points along the heading
    rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    r, p = math.radians(roll_deg), math.radians(pitch_deg)
    ry = np.array([[math.cos(r), 0.0, -math.sin(r)], [0.0, 1.0, 0.0], [math.sin(r), 0.0, math.cos(r)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), math.sin(p)], [0.0, -math.sin(p), math.cos(p)]])
    return rx @ ry @ base @ rz


@dataclass(frozen=True, eq=False)
class FrameCamera:
    """A pinhole camera with Brown distortion and a pose.

    Parameters
    ----------
    fx, fy : float
        Focal length, pixels.
    cx, cy : float
        Principal point, GDAL pixel convention (column, row).
    rows, cols : int
        Image size, pixels.
    crs : str
        Projected CRS of the world frame (e.g. a UTM zone).
    position : (float, float, float)
        Perspective centre ``(E, N, h)``, metres.
    rotation : (3, 3) array
        World-to-camera rotation ``R`` (module docstring).
    k1, k2, k3, p1, p2 : float
        Brown/OpenCV distortion coefficients (of normalised coordinates).
    pixel_size_mm : float or None
        Detector pitch, millimetres (focal-plane distances for radial
        selection); None when unknown.
    source : str
        Where the model came from, for messages.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    rows: int
    cols: int
    crs: str
    position: tuple[float, float, float]
    rotation: np.ndarray
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    pixel_size_mm: float | None = None
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = f" ({self.source})" if self.source else ""
        R = np.asarray(self.rotation, float)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise RPCError(f"frame camera{where}: rotation must be a proper 3x3 rotation matrix, got {R.tolist()}")
        object.__setattr__(self, "rotation", R)
        pos = tuple(float(v) for v in np.asarray(self.position, float).ravel())
        if len(pos) != 3 or not all(math.isfinite(v) for v in pos):
            raise RPCError(f"frame camera{where}: position must be 3 finite numbers (E, N, h), got {self.position!r}")
        object.__setattr__(self, "position", pos)
        for name in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise RPCError(f"frame camera{where}: {name} is not finite")
            object.__setattr__(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise RPCError(f"frame camera{where}: focal lengths must be > 0 pixels, got fx={self.fx}, fy={self.fy}")
        for name in ("rows", "cols"):
            v = getattr(self, name)
            if int(v) != v or int(v) <= 0:
                raise RPCError(f"frame camera{where}: {name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))

    def replace(self, **changes) -> "FrameCamera":
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_opencv(cls, K, dist, rvec, tvec, shape: tuple[int, int], crs: str, **kwargs) -> "FrameCamera":
        """From OpenCV's calibration and pose.

        ``K`` is the 3x3 camera matrix (principal point in OpenCV's
        pixel-centre convention), ``dist`` ``(k1, k2, p1, p2[, k3])``,
        ``rvec``/``tvec`` the world-to-camera pose (``X_c = R X + t``, world
        in ``crs`` metres with ellipsoidal heights), ``shape`` ``(rows, cols)``.
        """
        K = np.asarray(K, float)
        d = list(np.asarray(dist, float).ravel()) + [0.0] * 5
        R = rodrigues(rvec)
        C = -R.T @ np.asarray(tvec, float).ravel()
        return cls(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5, rows=shape[0], cols=shape[1],
                   crs=crs, position=tuple(C), rotation=R, k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4], **kwargs)

    def opencv(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(K, dist, rvec, tvec)`` in OpenCV's conventions (inverse of
        :meth:`from_opencv`)."""
        import cv2

        K = np.array([[self.fx, 0.0, self.cx - 0.5], [0.0, self.fy, self.cy - 0.5], [0.0, 0.0, 1.0]])
        rvec, _ = cv2.Rodrigues(self.rotation)
        tvec = -self.rotation @ np.asarray(self.position)
        return K, np.array([self.k1, self.k2, self.p1, self.p2, self.k3]), rvec.ravel(), tvec

    # ------------------------------------------------------------ pinhole maths
    def distort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Brown distortion of normalised coordinates."""
        r2 = x * x + y * y
        q = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * q + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * q + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def undistort(self, xd, yd, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Invert :meth:`distort` by Newton iterations (analytic Jacobian)."""
        x, y = np.array(xd, float, copy=True), np.array(yd, float, copy=True)
        if self.k1 == self.k2 == self.k3 == self.p1 == self.p2 == 0.0:
            return x, y
        for _ in range(iterations):
            fx_, fy_ = self.distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            r2 = x * x + y * y
            q = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            dq = 2.0 * (self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2))  # dq/dr2 * 2
            a = q + x * x * dq + 2.0 * self.p1 * y + 6.0 * self.p2 * x
            b = x * y * dq + 2.0 * self.p1 * x + 2.0 * self.p2 * y
            c = x * y * dq + 2.0 * self.p1 * x + 2.0 * self.p2 * y
            d = q + y * y * dq + 6.0 * self.p1 * y + 2.0 * self.p2 * x
            det = a * d - b * c
            x = x - (d * ex - b * ey) / det
            y = y - (-c * ex + a * ey) / det
            if np.all(np.abs(ex) + np.abs(ey) < 1e-14):
                break
        return x, y

    def project_xyz(self, e, n, h) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (``crs`` metres, ellipsoidal heights) to
        GDAL pixels ``(row, col)``; NaN behind the camera."""
        e, n, h = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float), np.asarray(h, float))
        C = self.position
        X = np.stack([e - C[0], n - C[1], h - C[2]])
        xc = np.tensordot(self.rotation, X, axes=(1, 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(xc[2] > 0, xc[2], np.nan)
            xd, yd = self.distort(xc[0] / z, xc[1] / z)
        return self.fy * yd + self.cy, self.fx * xd + self.cx

    def localize_xyz(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:
        """World ``(E, N)`` (``crs`` metres) of pixels at ellipsoidal height ``h``."""
        row, col, h = np.broadcast_arrays(np.asarray(row, float), np.asarray(col, float), np.asarray(h, float))
        x, y = self.undistort((col - self.cx) / self.fx, (row - self.cy) / self.fy)
        d = np.tensordot(self.rotation.T, np.stack([x, y, np.ones_like(x)]), axes=(1, 0))
        C = self.position
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (h - C[2]) / d[2]
        t = np.where(t > 0, t, np.nan)
        return C[0] + t * d[0], C[1] + t * d[1]

    # ------------------------------------------------------------ Camera protocol
    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        """Ground ``(lon, lat)`` degrees, ``h`` ellipsoidal metres -> GDAL
        pixel ``(row, col)`` (NaN behind the camera)."""
        e, n = transformer("EPSG:4326", self.crs).transform(np.asarray(lon, float), np.asarray(lat, float))
        return self.project_xyz(np.asarray(e), np.asarray(n), h)

    def localize(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:
        """GDAL pixel ``(row, col)`` at ellipsoidal height ``h`` -> ``(lon, lat)``
        degrees (NaN where the ray does not reach ``h`` in front of the camera)."""
        e, n = self.localize_xyz(row, col, h)
        lon, lat = transformer(self.crs, "EPSG:4326").transform(e, n)
        return np.asarray(lon), np.asarray(lat)

    # ------------------------------------------------------------ focal plane
    def focal_plane_radius(self, row, col) -> np.ndarray:
        """Distance of image points from the principal point on the focal
        plane: millimetres when ``pixel_size_mm`` is known, else pixels."""
        r = np.hypot(np.asarray(row, float) - self.cy, np.asarray(col, float) - self.cx)
        return r * self.pixel_size_mm if self.pixel_size_mm else r
