"""``tiledsm info FILE``: what a raster is, which camera it has, what it sees."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_parser", "describe"]


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "info",
        help="describe an image or DSM: size, dtype, camera, footprint, heights, GSD",
        description="Describe an image (camera model and where it came from, ground footprint, "
        "RPC height range, GSD estimate) or a DSM product (CRS, resolution, height statistics).",
    )
    p.add_argument("file", help="GeoTIFF/NITF/zarr image or DSM")
    p.add_argument("--rpc", default=None, help="explicit RPC file for the image")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)


def describe(path: str | Path, rpc: str | Path | None = None) -> dict:
    """Facts about a raster, measured from the file (see ``tiledsm info``).

    Returns a JSON-serialisable dict. For an image with a camera: the
    footprint corners (lon, lat, degrees) localised at the RPC's mid height,
    the RPC height validity range (metres, ellipsoidal) and the ground sample
    distance (metres per pixel) measured at the image centre.
    """
    import numpy as np
    import rasterio
    from pyproj import Geod

    from tiledsm.errors import InputFileError, RPCError
    from tiledsm.io.cameras import find_camera

    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: no such file")
    try:
        ds = rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise InputFileError(f"{path}: not a readable raster ({exc})") from exc
    with ds:
        out: dict = {
            "file": str(path),
            "driver": ds.driver,
            "width": ds.width,
            "height": ds.height,
            "bands": ds.count,
            "dtype": ds.dtypes[0],
            "nodata": ds.nodata,
            "crs": ds.crs.to_string() if ds.crs else None,
        }
        if ds.crs is not None:
            out["resolution"] = [abs(ds.transform.a), abs(ds.transform.e)]
            out["bounds"] = list(ds.bounds)
            data = ds.read(1, masked=True).astype("float64").filled(np.nan)
            if ds.dtypes[0].startswith("float"):
                finite = np.isfinite(data)
                out["valid_fraction"] = float(finite.mean())
                if finite.any():
                    out["value_range"] = [float(np.nanmin(data)), float(np.nanmax(data))]
    try:
        camera, source = find_camera(path, rpc)
    except RPCError as exc:
        out["camera"] = None
        out["camera_error"] = str(exc)
        return out
    h_mid = camera.height_off
    w, h = out["width"], out["height"]
    rows = np.array([0, 0, h, h], float)
    cols = np.array([0, w, w, 0], float)
    lon, lat = camera.localize(rows, cols, h_mid)
    geod = Geod(ellps="WGS84")
    clon, clat = camera.localize(np.array([h / 2, h / 2 + 1, h / 2]), np.array([w / 2, w / 2, w / 2 + 1]), h_mid)
    _, _, d_row = geod.inv(clon[0], clat[0], clon[1], clat[1])
    _, _, d_col = geod.inv(clon[0], clat[0], clon[2], clat[2])
    out.update(
        camera="RPC",
        camera_source=source,
        footprint_lonlat=[[float(a), float(b)] for a, b in zip(lon, lat)],
        rpc_height_range=[camera.height_off - camera.height_scale, camera.height_off + camera.height_scale],
        gsd_m={"row": float(d_row), "col": float(d_col)},
    )
    return out


def run(args: argparse.Namespace) -> int:
    info = describe(args.file, args.rpc)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    from rich.console import Console
    from rich.table import Table

    table = Table(title=str(info["file"]), show_header=False)
    for key, value in info.items():
        if key == "file":
            continue
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list) and value and isinstance(value[0], list):
            value = "\n".join(f"{a:.6f}, {b:.6f}" for a, b in value)
        elif isinstance(value, dict):
            value = ", ".join(f"{k}={v:.4g}" for k, v in value.items())
        table.add_row(key, str(value))
    Console().print(table)
    return 0
