"""The camera protocol shared by every camera model (RPC, frame camera).

A camera maps ground points to image points and back, vectorised:

- ``project(lon, lat, h) -> (row, col)``
- ``localize(row, col, h) -> (lon, lat)``

Conventions
-----------
- Pixel coordinates are GDAL's: the top-left corner of the image is
  ``(row, col) = (0, 0)`` and array element ``[i, j]`` has its centre at
  ``(i + 0.5, j + 0.5)``.
- Ground points are WGS84 longitude/latitude (degrees) and heights in
  metres above the WGS84 ellipsoid.
- Every method broadcasts over numpy arrays of any shape; points a camera
  cannot image (behind a frame camera) are NaN.

:class:`tiledsm.geometry.rpc.RPC` and :class:`tiledsm.geometry.frame.FrameCamera`
satisfy the protocol; :func:`height_parallax` is what geometry needs from
any of them beyond it.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["Camera", "GroundShifted", "height_parallax"]


@runtime_checkable
class Camera(Protocol):
    """Anything with ``project``/``localize`` in the module's conventions."""

    source: str

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - protocol
        """Ground (degrees, ellipsoidal metres) -> GDAL pixel ``(row, col)``."""
        ...

    def localize(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - protocol
        """GDAL pixel ``(row, col)`` at ellipsoidal height ``h`` -> ``(lon, lat)`` degrees."""
        ...


def height_parallax(camera: Camera, crs: str, x, y, h, step: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal shift of a line of sight per metre of height.

    For the ground point ``(x, y, h)`` (``crs`` metres, ellipsoidal height),
    the point ``(x + vx dh, y + vy dh, h + dh)`` projects to the same pixel
    (to first order): ``(vx, vy)`` points from the ground point towards the
    sensor's ground nadir, with ``|v| = tan(off-nadir angle)``. It is
    measured with four ``project`` calls (central differences of
    ``step`` metres in x, y and h), so it works for any camera.

    Returns
    -------
    vx, vy : numpy.ndarray
        Metres of horizontal shift per metre of height (broadcast shape).
    """
    from tiledsm.geometry.footprint import to_lonlat

    x, y, h = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(h, float))
    lon_x0, lat_x0 = to_lonlat(crs, x - step, y)
    lon_x1, lat_x1 = to_lonlat(crs, x + step, y)
    lon_y0, lat_y0 = to_lonlat(crs, x, y - step)
    lon_y1, lat_y1 = to_lonlat(crs, x, y + step)
    lon, lat = to_lonlat(crs, x, y)
    rx0, cx0 = camera.project(lon_x0, lat_x0, h)
    rx1, cx1 = camera.project(lon_x1, lat_x1, h)
    ry0, cy0 = camera.project(lon_y0, lat_y0, h)
    ry1, cy1 = camera.project(lon_y1, lat_y1, h)
    rh0, ch0 = camera.project(lon, lat, h - step)
    rh1, ch1 = camera.project(lon, lat, h + step)
    d = 2.0 * step
    a, b = (rx1 - rx0) / d, (ry1 - ry0) / d  # drow/dx, drow/dy
    c, e = (cx1 - cx0) / d, (cy1 - cy0) / d  # dcol/dx, dcol/dy
    gr, gc = (rh1 - rh0) / d, (ch1 - ch0) / d  # drow/dh, dcol/dh
    det = a * e - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        # J (vx, vy) = -(gr, gc)
        vx = -(e * gr - b * gc) / det
        vy = -(-c * gr + a * gc) / det
    return vx, vy


class GroundShifted:
    """A camera whose ground is translated: ``project(P) = camera.project(P + t)``
    with ``t = (dx, dy)`` metres in ``crs`` (and ``localize`` the inverse).

    This is how an image-to-image registration measured on orthos (the
    content of ortho cell ``q + t`` matches the reference's cell ``q``) is
    folded into the camera, so the registered ortho is resampled once.
    """

    def __init__(self, camera: Camera, crs: str, dx: float, dy: float):
        self.camera, self.crs, self.dx, self.dy = camera, str(crs), float(dx), float(dy)
        self.source = f"{getattr(camera, 'source', '')} shifted ({dx:+.4f}, {dy:+.4f}) m".strip()

    def _shift(self, lon, lat, sign: float):
        from tiledsm.geometry.footprint import to_lonlat
        from tiledsm.geometry.frame import transformer

        x, y = transformer("EPSG:4326", self.crs).transform(np.asarray(lon, float), np.asarray(lat, float))
        return to_lonlat(self.crs, np.asarray(x) + sign * self.dx, np.asarray(y) + sign * self.dy)

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        return self.camera.project(*self._shift(lon, lat, 1.0), h)

    def localize(self, row, col, h) -> tuple[np.ndarray, np.ndarray]:
        return self._shift(*self.camera.localize(row, col, h), -1.0)
