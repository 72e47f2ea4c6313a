"""Frame-camera files: a simple YAML block file and OpenCV calibrations.

The YAML block file (what :func:`write_cameras_yaml` writes)::

    crs: EPSG:32631                    # world frame: E, N (metres), ellipsoidal h
    principal_point: gdal              # gdal | colmap (corner at 0) | opencv (centre at 0)
    intrinsics:                        # shared by every image (or per image)
      fx: 1000.0                       # pixels
      fy: 1000.0
      cx: 320.0
      cy: 240.0
      k1: 0.0                          # Brown/OpenCV distortion (optional)
      k2: 0.0
      k3: 0.0
      p1: 0.0
      p2: 0.0
      width: 640                       # pixels
      height: 480
      pixel_size_mm: 0.005             # optional (radial selection in mm)
      # or: calibration: calib.yml     # OpenCV FileStorage (camera_matrix, distortion_coefficients)
    images:
      - image: frame_000.tif           # relative to the YAML file
        position: [E, N, h]            # perspective centre, metres
        rotation: [[..], [..], [..]]   # world -> camera (x right, y down, z forward)
      - image: frame_001.tif
        rvec: [..]                     # or OpenCV's pose: X_c = R(rvec) X + tvec
        tvec: [..]

Every error names the file and the field (:class:`CameraFileError`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from tiledsm.errors import InputFileError
from tiledsm.geometry.frame import FrameCamera, rodrigues

__all__ = ["CameraFileError", "read_cameras_yaml", "write_cameras_yaml", "read_opencv_calibration", "camera_for_image"]

_CONVENTIONS = {"gdal": 0.0, "colmap": 0.0, "opencv": 0.5}
_DIST = ("k1", "k2", "k3", "p1", "p2")


class CameraFileError(InputFileError):
    """Raised when a camera file is missing, malformed or lacks a field;
    the message names the file and the field path."""


def read_opencv_calibration(path: str | os.PathLike) -> dict:
    """Intrinsics from an OpenCV ``FileStorage`` file (YAML/XML as written
    by ``cv2.FileStorage`` or OpenCV's calibration sample): nodes
    ``camera_matrix``, ``distortion_coefficients`` (``k1 k2 p1 p2 [k3]``),
    ``image_width``, ``image_height``.

    Returns
    -------
    dict
        ``fx, fy, cx, cy`` (OpenCV convention: pixel centre at 0), the
        distortion coefficients, ``width``, ``height``.
    """
    import cv2

    p = Path(path)
    if not p.is_file():
        raise CameraFileError(f"{p}: no such calibration file")
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise CameraFileError(f"{p}: not an OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        if K is None or K.shape != (3, 3):
            raise CameraFileError(f"{p}: camera_matrix missing or not 3x3")
        dnode = fs.getNode("distortion_coefficients")
        d = [] if dnode.empty() else list(np.asarray(dnode.mat(), float).ravel())
        d += [0.0] * (5 - len(d))
        w, h = fs.getNode("image_width").real(), fs.getNode("image_height").real()
    finally:
        fs.release()
    if not (w > 0 and h > 0):
        raise CameraFileError(f"{p}: image_width / image_height missing")
    return dict(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4],
                width=int(w), height=int(h))


def _number(doc: Mapping, key: str, where: str, default=None) -> float:
    if key not in doc or doc[key] is None:
        if default is None:
            raise CameraFileError(f"{where}.{key}: missing (expected a number)")
        return float(default)
    try:
        return float(doc[key])
    except (TypeError, ValueError):
        raise CameraFileError(f"{where}.{key}: expected a number, got {doc[key]!r}") from None


def _intrinsics(doc: Mapping, base: Path, where: str) -> tuple[dict, float | None]:
    """Intrinsics dict, and the offset of its principal point to GDAL's
    convention when it comes from an OpenCV calibration (None: the file's
    ``principal_point`` convention applies)."""
    if not isinstance(doc, Mapping):
        raise CameraFileError(f"{where}: expected a mapping of fx, fy, cx, cy, width, height, ...")
    doc = dict(doc)
    if "calibration" in doc:
        cal = read_opencv_calibration(base / str(doc.pop("calibration")))
        return {**cal, **doc}, _CONVENTIONS["opencv"]
    return doc, None


def read_cameras_yaml(path: str | os.PathLike) -> dict[str, FrameCamera]:
    """Read a YAML block file (module docstring).

    Returns
    -------
    dict
        Absolute image path (str) -> :class:`FrameCamera` (principal point
        converted to GDAL's convention).
    """
    import yaml

    p = Path(path)
    if not p.is_file():
        raise CameraFileError(f"{p}: no such camera file")
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise CameraFileError(f"{p}: not valid YAML ({exc})") from exc
    if not isinstance(doc, Mapping):
        raise CameraFileError(f"{p}: expected a mapping with crs, intrinsics and images")
    base = p.parent
    crs = doc.get("crs")
    if not crs:
        raise CameraFileError(f"{p}: crs: missing (the projected CRS of positions, e.g. EPSG:32631)")
    conv = str(doc.get("principal_point", "gdal")).lower()
    if conv not in _CONVENTIONS:
        raise CameraFileError(f"{p}: principal_point: expected one of {sorted(_CONVENTIONS)}, got {conv!r}")
    shared = doc.get("intrinsics")
    images = doc.get("images")
    if not isinstance(images, list) or not images:
        raise CameraFileError(f"{p}: images: expected a non-empty list")
    out: dict[str, FrameCamera] = {}
    for k, entry in enumerate(images):
        where = f"{p}: images[{k}]"
        if not isinstance(entry, Mapping) or "image" not in entry:
            raise CameraFileError(f"{where}.image: missing")
        intr_doc = entry.get("intrinsics", shared)
        if intr_doc is None:
            raise CameraFileError(f"{where}.intrinsics: missing (and no shared intrinsics)")
        intr, offset = _intrinsics(intr_doc, base, f"{where}.intrinsics")
        offset = _CONVENTIONS[conv] if offset is None else offset
        wi = f"{where}.intrinsics"
        vals = {key: _number(intr, key, wi) for key in ("fx", "fy", "cx", "cy", "width", "height")}
        dist = {key: _number(intr, key, wi, 0.0) for key in _DIST}
        pix = intr.get("pixel_size_mm")
        if "rotation" in entry and "position" in entry:
            R = np.asarray(entry["rotation"], float)
            C = np.asarray(entry["position"], float)
        elif "rvec" in entry and "tvec" in entry:
            R = rodrigues(entry["rvec"])
            C = -R.T @ np.asarray(entry["tvec"], float).ravel()
        else:
            raise CameraFileError(f"{where}: pose missing (give position + rotation, or rvec + tvec)")
        image = (base / str(entry["image"])).resolve()
        try:
            cam = FrameCamera(
                fx=vals["fx"], fy=vals["fy"], cx=vals["cx"] + offset, cy=vals["cy"] + offset,
                rows=int(vals["height"]), cols=int(vals["width"]), crs=str(crs), position=tuple(C), rotation=R,
                pixel_size_mm=None if pix is None else float(pix), source=f"{p} ({entry['image']})", **dist,
            )
        except (ValueError, TypeError) as exc:
            raise CameraFileError(f"{where}: {exc}") from exc
        out[str(image)] = cam
    return out


def camera_for_image(cameras_file: str | os.PathLike, image: str | os.PathLike) -> FrameCamera:
    """The camera of ``image`` in a YAML block file (matched by resolved
    path, then by file name)."""
    return match_camera(read_cameras_yaml(cameras_file), image, cameras_file)


def match_camera(cams: Mapping[str, FrameCamera], image: str | os.PathLike,
                 cameras_file: str | os.PathLike) -> FrameCamera:
    """The camera of ``image`` among a block file's cameras
    (:func:`read_cameras_yaml`): by resolved path, then by file name."""
    img = Path(image).resolve()
    if str(img) in cams:
        return cams[str(img)]
    by_name = [c for k, c in cams.items() if Path(k).name == img.name]
    if len(by_name) == 1:
        return by_name[0]
    raise CameraFileError(f"{cameras_file}: images: no entry for {img.name} (entries: {[Path(k).name for k in cams]})")


def write_cameras_yaml(path: str | os.PathLike, cameras: Mapping[str, FrameCamera]) -> Path:
    """Write cameras (image path relative to the YAML -> camera) as a YAML
    block file in GDAL's principal-point convention, atomically."""
    import yaml

    from tiledsm.io import atomic_path

    cams = list(cameras.items())
    if not cams:
        raise ValueError("write_cameras_yaml: no cameras")
    crs = cams[0][1].crs

    def intr(c: FrameCamera) -> dict:
        d = dict(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width=c.cols, height=c.rows,
                 **{k: getattr(c, k) for k in _DIST})
        if c.pixel_size_mm:
            d["pixel_size_mm"] = c.pixel_size_mm
        return d

    first = intr(cams[0][1])
    doc = {"crs": crs, "principal_point": "gdal", "intrinsics": first, "images": []}
    for name, c in cams:
        if c.crs != crs:
            raise ValueError(f"write_cameras_yaml: {name} is in {c.crs}, the block in {crs}")
        e = {"image": str(name), "position": [float(v) for v in c.position],
             "rotation": np.asarray(c.rotation).tolist()}
        if intr(c) != first:
            e["intrinsics"] = intr(c)
        doc["images"].append(e)
    final = Path(path)
    with atomic_path(final) as tmp:
        Path(tmp).write_text(yaml.safe_dump(doc, sort_keys=False))
    return final
