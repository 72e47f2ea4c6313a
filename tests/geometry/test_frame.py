"""Frame camera: OpenCV's projectPoints, round trips, the camera protocol."""

import cv2
import numpy as np
import pytest
from pyproj import Transformer

from tiledsm.errors import RPCError
from tiledsm.geometry.camera import Camera, height_parallax
from tiledsm.geometry.frame import FrameCamera, rodrigues, rotation_nadir
from tiledsm.geometry.rpc import RPC

CRS = "EPSG:32631"
E0, N0 = 640000.0, 4890000.0


def _camera(**kw):
    args = dict(fx=1200.0, fy=1210.0, cx=330.2, cy=241.7, rows=480, cols=640, crs=CRS,
                position=(E0 + 3.0, N0 - 5.0, 180.0), rotation=rotation_nadir(35.0, 2.0, -3.0),
                k1=-0.12, k2=0.05, k3=-0.01, p1=0.001, p2=-0.0007)
    args.update(kw)
    return FrameCamera(**args)


def _lonlat(e, n):
    return Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(e, n)


def test_project_equals_opencv_projectpoints():
    cam = _camera()
    rng = np.random.default_rng(0)
    e = E0 + rng.uniform(-40, 40, 200)
    n = N0 + rng.uniform(-30, 30, 200)
    h = rng.uniform(90, 110, 200)
    K, dist, rvec, tvec = cam.opencv()
    # cv2 on coordinates relative to a local origin (float64 throughout)
    R = cam.rotation
    t_local = tvec + R @ np.array([E0, N0, 0.0])
    uv, _ = cv2.projectPoints(np.stack([e - E0, n - N0, h], 1), rvec, t_local, K, dist)
    row, col = cam.project(*_lonlat(e, n), h)
    np.testing.assert_allclose(col, uv[:, 0, 0] + 0.5, atol=1e-6)  # GDAL = OpenCV + 0.5
    np.testing.assert_allclose(row, uv[:, 0, 1] + 0.5, atol=1e-6)


def test_from_opencv_round_trip_and_rodrigues():
    cam = _camera()
    K, dist, rvec, tvec = cam.opencv()
    np.testing.assert_allclose(rodrigues(rvec), cv2.Rodrigues(rvec)[0], atol=1e-12)
    back = FrameCamera.from_opencv(K, dist, rvec, tvec, (480, 640), CRS)
    for f in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"):
        assert getattr(back, f) == pytest.approx(getattr(cam, f), abs=1e-12)
    np.testing.assert_allclose(back.position, cam.position, atol=1e-6)


def test_localize_inverts_project():
    cam = _camera()
    rows, cols = np.meshgrid(np.linspace(0, 480, 13), np.linspace(0, 640, 17), indexing="ij")
    h = 95.0 + 0 * rows
    lon, lat = cam.localize(rows, cols, h)
    r2, c2 = cam.project(lon, lat, h)
    assert np.abs(r2 - rows).max() < 1e-7 and np.abs(c2 - cols).max() < 1e-7
    # undistortion agrees with OpenCV's
    K, dist, _, _ = cam.opencv()
    pts = np.stack([cols.ravel() - 0.5, rows.ravel() - 0.5], 1)[:, None, :]
    und = cv2.undistortPoints(pts, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))
    x, y = cam.undistort((cols.ravel() - cam.cx) / cam.fx, (rows.ravel() - cam.cy) / cam.fy)
    np.testing.assert_allclose(x, und[:, 0, 0], atol=1e-6)
    np.testing.assert_allclose(y, und[:, 0, 1], atol=1e-6)


def test_nadir_geometry_and_behind_is_nan():
    cam = FrameCamera(1000.0, 1000.0, 320.0, 240.0, 480, 640, CRS, (E0, N0, 200.0), rotation_nadir())
    # a point 10 m north, 20 m east of the nadir at h = 100 (100 m below): 100 px up, 200 px right
    r, c = cam.project_xyz(E0 + 20.0, N0 + 10.0, 100.0)
    assert r == pytest.approx(240.0 - 100.0) and c == pytest.approx(320.0 + 200.0)
    # heading 90: image top points east
    cam90 = cam.replace(rotation=rotation_nadir(90.0))
    r, c = cam90.project_xyz(E0 + 10.0, N0, 100.0)
    assert r == pytest.approx(140.0) and c == pytest.approx(320.0)
    r, c = cam.project_xyz(E0, N0, 300.0)  # above the camera
    assert np.isnan(r) and np.isnan(c)
    # focal-plane radius
    cam_mm = cam.replace(pixel_size_mm=0.004)
    assert cam_mm.focal_plane_radius(240.0 + 30.0, 320.0 + 40.0) == pytest.approx(0.2)


def test_protocol_and_height_parallax():
    cam = FrameCamera(1000.0, 1000.0, 320.0, 240.0, 480, 640, CRS, (E0, N0, 200.0), rotation_nadir())
    assert isinstance(cam, Camera)
    coeffs = np.zeros(20)
    coeffs[0] = 1.0
    rpc = RPC(0, 0, 0, 0, 0, 1, 1, 1, 1, 1, coeffs, coeffs, coeffs, coeffs)
    assert isinstance(rpc, Camera)
    # a ground point 30 m east of the nadir, 100 m below: moving up the ray towards the camera goes 0.3 m west, 0.15 m north per metre
    vx, vy = height_parallax(cam, CRS, E0 + 30.0, N0 - 15.0, 100.0)
    assert vx == pytest.approx(-0.3, abs=1e-5) and vy == pytest.approx(0.15, abs=1e-5)


def test_bad_rotation_is_refused():
    with pytest.raises(RPCError, match="rotation must be a proper 3x3 rotation"):
        _camera(rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(RPCError, match="focal lengths must be > 0"):
        _camera(fx=0.0)
