"""Stable terrain: where the ground is assumed not to have moved.

A cell is *stable* when it is

1. outside every polygon of the exclusion file (GeoJSON; e.g. the rupture
   zone, landslides, glaciers, new buildings), rasterised with
   ``rasterio.features.geometry_mask`` (a cell is excluded when its centre is
   inside a polygon),
2. no steeper than ``max_slope_deg`` on the reference DSM, and
3. not an outlier: ``|dh - median| <= k * NMAD`` (``median`` and ``NMAD`` of
   stable ``dh`` measured on the co-registration sample).

The polygons keep the deformation signal out of the co-registration fit; the
slope and outlier filters are applied automatically.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import dask.array as da
import numpy as np
from affine import Affine

from tiledsm.errors import InputFileError

__all__ = ["read_polygons", "exclusion_mask", "exclusion_mask_lazy", "stable_cells", "polygons_touch"]

_POLY_TYPES = ("Polygon", "MultiPolygon")


def read_polygons(path: str | Path, dst_crs) -> list[dict]:
    """Polygons of a GeoJSON file as GeoJSON geometries in ``dst_crs``.

    The file's CRS is WGS84 lon/lat (RFC 7946) unless it carries a legacy
    ``"crs": {"properties": {"name": ...}}`` member. FeatureCollection,
    Feature, Polygon, MultiPolygon and GeometryCollection are accepted;
    non-polygon geometries are refused.

    Raises
    ------
    InputFileError
        Missing file, invalid JSON, no polygon, or a non-polygon geometry.
    """
    from rasterio.crs import CRS
    from rasterio.warp import transform_geom

    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: no such stable-mask (GeoJSON) file")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: not valid GeoJSON ({exc})") from exc
    src_crs = CRS.from_epsg(4326)
    name = (doc.get("crs") or {}).get("properties", {}).get("name") if isinstance(doc, dict) else None
    if name:
        try:
            src_crs = CRS.from_user_input(name)
        except Exception as exc:
            raise InputFileError(f"{path}: unknown crs {name!r} ({exc})") from exc
    geoms: list[dict] = []

    def collect(obj, where: str):
        if not isinstance(obj, dict) or "type" not in obj:
            raise InputFileError(f"{path}: {where} is not a GeoJSON object")
        t = obj["type"]
        if t == "FeatureCollection":
            for i, f in enumerate(obj.get("features", [])):
                collect(f, f"features[{i}]")
        elif t == "Feature":
            if obj.get("geometry") is not None:
                collect(obj["geometry"], f"{where}.geometry")
        elif t == "GeometryCollection":
            for i, g in enumerate(obj.get("geometries", [])):
                collect(g, f"{where}.geometries[{i}]")
        elif t in _POLY_TYPES:
            geoms.append(obj)
        else:
            raise InputFileError(f"{path}: {where} is a {t}; only Polygon/MultiPolygon areas can be excluded")

    collect(doc, "root")
    if not geoms:
        raise InputFileError(f"{path}: no polygon found")
    if not name:
        _check_degrees(path, geoms)
    if src_crs != dst_crs:
        try:
            geoms = [transform_geom(src_crs, dst_crs, g) for g in geoms]
        except Exception as exc:  # rasterio/PROJ raise several types
            raise InputFileError(f"{path}: its polygons cannot be transformed from {src_crs} to {dst_crs} ({exc})") from None
    return geoms


def _check_degrees(path: Path, geoms: list[dict]) -> None:
    """Refuse polygons of a GeoJSON without ``crs`` member whose coordinates
    are not longitude/latitude degrees. RFC 7946 makes such a file WGS84;
    metres there are a projected file whose ``crs`` was dropped. Guessing the
    DSM's CRS could exclude the wrong ground silently, so the user says."""
    try:
        xy = np.array([pt[:2] for g in geoms for ring in _rings(g) for pt in ring], dtype=float).reshape(-1, 2)
    except (TypeError, ValueError, IndexError) as exc:
        raise InputFileError(f"{path}: malformed polygon coordinates ({exc})") from None
    outside = (np.abs(xy[:, 0]) > 180) | (np.abs(xy[:, 1]) > 90)
    if outside.any():
        x, y = xy[np.argmax(outside)]
        raise InputFileError(
            f"{path}: coordinates such as ({x:g}, {y:g}) are not longitude/latitude degrees, the CRS of a GeoJSON "
            'without a "crs" member (RFC 7946); add one naming its CRS, e.g. "crs": {"type": "name", '
            '"properties": {"name": "EPSG:32631"}}, or reproject it to EPSG:4326')


def _rings(geom: dict) -> list:
    """The coordinate rings of a Polygon or MultiPolygon."""
    coords = geom.get("coordinates") or []
    return list(coords) if geom["type"] == "Polygon" else [ring for poly in coords for ring in poly]


def exclusion_mask(geoms: list[dict], transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """True where a cell centre lies inside one of ``geoms`` (grid ``transform``)."""
    from rasterio.features import geometry_mask

    if not geoms:
        return np.zeros(shape, dtype=bool)
    return geometry_mask(geoms, out_shape=shape, transform=transform, invert=True)


def _mask_block(block, geoms, transform, block_info=None):
    (r0, _), (c0, _) = block_info[0]["array-location"]
    return exclusion_mask(geoms, transform @ Affine.translation(c0, r0), block.shape)


def exclusion_mask_lazy(geoms: list[dict], transform: Affine, like: da.Array) -> da.Array:
    """:func:`exclusion_mask` as a dask array with the chunks of ``like``."""
    if not geoms:
        return da.zeros(like.shape, chunks=like.chunks, dtype=bool)
    return da.map_blocks(_mask_block, like, geoms, transform, dtype=bool, meta=np.empty((0, 0), bool))


def stable_cells(dh, slope_deg, excluded, median: float, nmad_value: float, k: float, max_slope_deg: float):
    """Stable-terrain mask (numpy or dask): rules 1-3 of the module notes.

    NaN ``dh`` or slope is never stable.
    """
    ok = ~excluded & (slope_deg <= max_slope_deg)
    if nmad_value > 0:
        ok &= abs(dh - median) <= k * nmad_value
    else:
        ok &= dh == dh
    return ok


def polygons_touch(geoms: list[dict], box: Sequence[float]) -> bool:
    """Whether any GeoJSON polygon's bounding box meets ``box``
    ``(xmin, ymin, xmax, ymax)`` (same CRS)."""
    for g in geoms:
        rings = g["coordinates"] if g["type"] == "Polygon" else [r for p in g["coordinates"] for r in p]
        xy = np.concatenate([np.asarray(r, float)[:, :2] for r in rings])
        if xy[:, 0].min() <= box[2] and xy[:, 0].max() >= box[0] and xy[:, 1].min() <= box[3] and xy[:, 1].max() >= box[1]:
            return True
    return False
