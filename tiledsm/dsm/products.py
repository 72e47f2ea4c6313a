"""Derived products of a DSM: heights above a geoid."""

from __future__ import annotations

import json
from pathlib import Path

import dask.array as da
import numpy as np
import xarray as xr


# ------------------------------------------------------------------ products
def _geoid_block(height: np.ndarray, x: np.ndarray, y: np.ndarray, crs: str, geoid: str, block_info=None) -> np.ndarray:
    from tiledsm.geometry.footprint import to_lonlat
    from tiledsm.io.geoid import geoid_height

    (r0, r1), (c0, c1) = block_info[0]["array-location"]
    X, Y = np.meshgrid(x[c0:c1], y[r0:r1])
    lon, lat = to_lonlat(crs, X, Y)
    return (height - geoid_height(lon, lat, geoid)).astype(np.float32)


def heights_above_geoid(ds: xr.Dataset, geoid: str | Path) -> xr.Dataset:
    """The DSM with heights above the geoid of ``geoid`` instead of the
    WGS84 ellipsoid: ``H = h - N(lon, lat)``, chunk by chunk (lazy).

    Parameters
    ----------
    ds : xarray.Dataset
        Output of :func:`dsm_from_views` (``height`` in ellipsoidal metres,
        CRS written).
    geoid : path
        Geoid grid read by GDAL, e.g. EGM96 ``egm96_15.gtx``
        (see :mod:`tiledsm.io.geoid`).

    Raises
    ------
    InputFileError
        The grid is missing or unreadable (checked before anything runs).
    """
    from tiledsm.io.geoid import load_geoid

    geoid = str(Path(geoid))
    load_geoid(geoid)  # fail now, not inside a task
    h = ds["height"]
    data = da.map_blocks(
        _geoid_block, h.data, x=h.x.values, y=h.y.values, crs=ds.rio.crs.to_string(), geoid=geoid, dtype=np.float32
    )
    out = ds.copy()
    out["height"] = h.copy(data=data)
    if "fingerprint" in ds.attrs:
        from tiledsm.provenance import input_identity

        fp = json.loads(ds.attrs["fingerprint"])
        fp["geoid"] = input_identity(geoid)
        out.attrs["fingerprint"] = json.dumps(fp, sort_keys=True)
    out["height"].attrs.update(long_name=f"height above the geoid ({Path(geoid).name})", vertical_datum=Path(geoid).name)
    out.attrs["vertical_datum"] = f"geoid {Path(geoid).name}"
    return out
