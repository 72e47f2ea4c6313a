"""Camera files: YAML block file round trip, OpenCV FileStorage, errors."""

import cv2
import numpy as np
import pytest

from tiledsm.geometry.frame import FrameCamera, rotation_nadir
from tiledsm.ortho.cameras import CameraFileError, camera_for_image, read_cameras_yaml, write_cameras_yaml

CRS = "EPSG:32631"


def _cam(i):
    return FrameCamera(900.0, 901.0, 200.5, 150.25, 300, 400, CRS, (640000.0 + i, 4890000.0, 120.0),
                       rotation_nadir(10.0 * i, 1.0, -0.5), k1=-0.1, p2=0.001, pixel_size_mm=0.005)


def test_yaml_round_trip(tmp_path):
    cams = {f"f{i}.tif": _cam(i) for i in range(3)}
    write_cameras_yaml(tmp_path / "cams.yaml", cams)
    back = read_cameras_yaml(tmp_path / "cams.yaml")
    assert sorted(back) == sorted(str((tmp_path / n).resolve()) for n in cams)
    c = camera_for_image(tmp_path / "cams.yaml", tmp_path / "f2.tif")
    lon, lat = _cam(2).localize(np.array([10.0, 250.0]), np.array([30.0, 380.0]), 100.0)
    np.testing.assert_allclose(np.stack(c.project(lon, lat, 100.0)), [[10.0, 250.0], [30.0, 380.0]], atol=1e-8)
    assert c.pixel_size_mm == 0.005


def test_opencv_calibration_and_rvec_pose(tmp_path):
    cam = _cam(1)
    K, dist, rvec, tvec = cam.opencv()
    fs = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, 5))
    fs.write("image_width", 400)
    fs.write("image_height", 300)
    fs.release()
    (tmp_path / "cams.yaml").write_text(
        f"crs: {CRS}\nintrinsics:\n  calibration: calib.yml\nimages:\n"
        f"  - image: a.tif\n    rvec: {rvec.tolist()}\n    tvec: {tvec.tolist()}\n")
    got = camera_for_image(tmp_path / "cams.yaml", "a.tif")
    # OpenCV principal point (centre at 0) converted to GDAL's
    assert got.cx == pytest.approx(cam.cx) and got.cy == pytest.approx(cam.cy)
    np.testing.assert_allclose(got.position, cam.position, atol=1e-6)
    r, c = got.project_xyz(640001.0 + 5, 4890000.0 - 7, 100.0)
    r0, c0 = cam.project_xyz(640001.0 + 5, 4890000.0 - 7, 100.0)
    assert r == pytest.approx(r0, abs=1e-6) and c == pytest.approx(c0, abs=1e-6)


def test_errors_name_file_and_field(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(f"crs: {CRS}\nintrinsics: {{fx: 1, fy: 1, cx: 0, cy: 0, width: 10}}\nimages:\n  - image: a.tif\n"
                 "    position: [0, 0, 10]\n    rotation: [[1,0,0],[0,-1,0],[0,0,-1]]\n")
    with pytest.raises(CameraFileError, match=r"bad.yaml: images\[0\].intrinsics.height: missing"):
        read_cameras_yaml(p)
    p.write_text(f"crs: {CRS}\nintrinsics: {{fx: 1, fy: 1, cx: 0, cy: 0, width: 10, height: 10}}\n"
                 "images:\n  - image: a.tif\n    position: [0, 0, 10]\n")
    with pytest.raises(CameraFileError, match=r"images\[0\]: pose missing"):
        read_cameras_yaml(p)
    with pytest.raises(CameraFileError, match="no such camera file"):
        read_cameras_yaml(tmp_path / "none.yaml")
