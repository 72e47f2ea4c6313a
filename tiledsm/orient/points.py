"""Ground control and check points: reading CSV / GeoJSON files.

File formats
------------
CSV with the header ``id,image,lon,lat,h,row,col`` (column order free, extra
columns ignored), one line per *image measurement*: a point seen in two
images is two lines with the same ``id``, ground coordinates and ``image``
differing. ``image`` is the image file's name (matched against the names of
the images given, with or without folder); lon/lat are WGS84 degrees, ``h``
metres above the WGS84 ellipsoid; row/col are GDAL pixel coordinates (the
top-left corner of the image at (0, 0); the centre of pixel ``[i, j]`` at
``(i + .5, j + .5)``).

GeoJSON: a FeatureCollection of ``Point`` features with coordinates
``[lon, lat, h]`` and properties ``id``, ``image``, ``row``, ``col`` (the same
meaning); again one feature per image measurement.

A "duplicate id" is the same ``id`` measured twice in one image, or given
with different ground coordinates in two lines.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from tiledsm.errors import InputFileError

__all__ = ["ControlPoints", "read_points", "point_residuals", "CSV_COLUMNS"]

#: required CSV columns
CSV_COLUMNS = ("id", "image", "lon", "lat", "h", "row", "col")


@dataclass(frozen=True)
class ControlPoints:
    """Image measurements of ground points with known coordinates.

    Attributes
    ----------
    ids : numpy.ndarray
        ``(m,)`` str, point id of each measurement.
    image : numpy.ndarray
        ``(m,)`` int, index of the measured image (in the list given to
        :func:`read_points`).
    lon, lat, h : numpy.ndarray
        ``(m,)`` ground coordinates (degrees, degrees, metres ellipsoidal).
    row, col : numpy.ndarray
        ``(m,)`` measured pixel coordinates, GDAL convention.
    source : str
        The file read.
    """

    ids: np.ndarray
    image: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    row: np.ndarray
    col: np.ndarray
    source: str = ""

    def __len__(self) -> int:
        return int(self.ids.size)

    @property
    def point_ids(self) -> list[str]:
        """Distinct point ids, in order of first appearance."""
        return list(dict.fromkeys(self.ids.tolist()))

    def count_per_image(self, n_images: int) -> np.ndarray:
        return np.bincount(self.image, minlength=n_images)

    @classmethod
    def empty(cls) -> "ControlPoints":
        z = np.zeros(0)
        return cls(np.zeros(0, str), np.zeros(0, int), z, z, z, z, z)


def _rows_csv(path: Path, text: str) -> list[dict]:
    reader = csv.DictReader(text.splitlines())
    header = [h.strip().lower() for h in (reader.fieldnames or [])]
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise InputFileError(
            f"{path}: CSV header {','.join(header) or '(empty)'} lacks column(s) {', '.join(missing)}; "
            f"expected {','.join(CSV_COLUMNS)}"
        )
    rows = []
    for n, rec in enumerate(reader, start=2):
        rec = {(k or "").strip().lower(): (v or "").strip() for k, v in rec.items()}
        if not any(rec.values()):
            continue
        rec["_where"] = f"line {n}"
        rows.append(rec)
    return rows


def _rows_geojson(path: Path, text: str) -> list[dict]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(f"{path}: invalid JSON ({exc})") from exc
    feats = doc.get("features") if isinstance(doc, dict) else None
    if not isinstance(feats, list):
        raise InputFileError(f"{path}: not a GeoJSON FeatureCollection (no 'features' list)")
    rows = []
    for n, f in enumerate(feats):
        geom = (f or {}).get("geometry") or {}
        props = (f or {}).get("properties") or {}
        where = f"feature {n}"
        if geom.get("type") != "Point" or len(geom.get("coordinates") or []) != 3:
            raise InputFileError(f"{path}: {where}: expected a Point with coordinates [lon, lat, h]")
        missing = [k for k in ("id", "image", "row", "col") if k not in props]
        if missing:
            raise InputFileError(f"{path}: {where}: properties lack {', '.join(missing)} "
                                 "(expected id, image, row, col)")
        lon, lat, h = geom["coordinates"]
        rows.append({"id": str(props["id"]), "image": str(props["image"]), "lon": lon, "lat": lat, "h": h,
                     "row": props["row"], "col": props["col"], "_where": where})
    return rows


def _image_index(name: str, images: Sequence[str | Path]) -> int | None:
    names = [Path(p).name for p in images]
    n = Path(name).name
    if n in names:
        return names.index(n)
    stems = [Path(p).stem for p in images]
    return stems.index(Path(n).stem) if Path(n).stem in stems else None


def read_points(
    path: str | Path,
    images: Sequence[str | Path],
    shapes: Sequence[tuple[int, int]] | None = None,
) -> ControlPoints:
    """Read a GCP / check-point file (CSV or GeoJSON, see module docstring).

    Parameters
    ----------
    path : path-like
    images : sequence of path-like
        The images of the block; ``image`` fields are matched to their file
        names (or stems). Measurements of other images are an error.
    shapes : sequence of (rows, cols), optional
        Image sizes; a measurement outside its image is an error.

    Raises
    ------
    InputFileError
        Missing file, wrong columns, non-numeric or non-finite values, an
        unknown image, a point outside its image, or a duplicate id (the
        message names the file, the line/feature and the id).
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: no such points file")
    text = path.read_text(encoding="utf-8-sig")
    is_json = text.lstrip().startswith("{")
    rows = _rows_geojson(path, text) if is_json else _rows_csv(path, text)
    out: dict[str, list] = {k: [] for k in ("ids", "image", "lon", "lat", "h", "row", "col")}
    ground: dict[str, tuple[float, float, float]] = {}
    seen: set[tuple[str, int]] = set()
    for rec in rows:
        where = f"{path}: {rec['_where']}"
        pid = str(rec["id"])
        if not pid:
            raise InputFileError(f"{where}: empty id")
        vals = {}
        for k in ("lon", "lat", "h", "row", "col"):
            try:
                vals[k] = float(rec[k])
            except (TypeError, ValueError):
                raise InputFileError(f"{where}: {k} of point {pid!r} is not a number ({rec[k]!r})") from None
            if not np.isfinite(vals[k]):
                raise InputFileError(f"{where}: {k} of point {pid!r} is not finite")
        if not (-180 <= vals["lon"] <= 360 and -90 <= vals["lat"] <= 90):
            raise InputFileError(f"{where}: point {pid!r} lon/lat ({vals['lon']}, {vals['lat']}) are not degrees")
        idx = _image_index(str(rec["image"]), images)
        if idx is None:
            raise InputFileError(
                f"{where}: point {pid!r} is measured in image {rec['image']!r}, which is not one of "
                f"{', '.join(Path(p).name for p in images)}"
            )
        if (pid, idx) in seen:
            raise InputFileError(f"{where}: duplicate id {pid!r}: measured twice in {Path(images[idx]).name}")
        g = (vals["lon"], vals["lat"], vals["h"])
        if pid in ground and not np.allclose(ground[pid], g, rtol=0, atol=1e-9):
            raise InputFileError(f"{where}: duplicate id {pid!r} with other ground coordinates "
                                 f"({ground[pid]} before, {g} here)")
        if shapes is not None:
            nr, nc = shapes[idx]
            if not (0 <= vals["row"] <= nr and 0 <= vals["col"] <= nc):
                raise InputFileError(
                    f"{where}: point {pid!r} at row {vals['row']:g}, col {vals['col']:g} lies outside "
                    f"{Path(images[idx]).name} ({nr} x {nc} pixels, GDAL convention)"
                )
        seen.add((pid, idx))
        ground[pid] = g
        out["ids"].append(pid)
        out["image"].append(idx)
        for k in ("lon", "lat", "h", "row", "col"):
            out[k].append(vals[k])
    if not out["ids"]:
        raise InputFileError(f"{path}: no points")
    return ControlPoints(
        ids=np.array(out["ids"], dtype=str), image=np.array(out["image"], int),
        **{k: np.array(out[k], float) for k in ("lon", "lat", "h", "row", "col")}, source=str(path),
    )


def point_residuals(rpcs, pts: ControlPoints) -> np.ndarray:
    """``(n, 2)`` residuals ``(row, col)`` in pixels of every measurement of
    ``pts``: the projection of its ground point by the RPC of its image
    (``rpcs[pts.image[k]]``, GDAL pixel convention) minus the measured
    position."""
    out = np.full((len(pts), 2), np.nan)
    for i, rpc in enumerate(rpcs):
        m = pts.image == i
        if m.any():
            r, c = rpc.project(pts.lon[m], pts.lat[m], pts.h[m])
            out[m] = np.column_stack([r - pts.row[m], c - pts.col[m]])
    return out
