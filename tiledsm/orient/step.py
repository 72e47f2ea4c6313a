"""The step a ``dsm`` (or ``deformation``) recipe with an ``orient:``
section runs first: its images oriented
(:func:`tiledsm.orient.stage.orient_images`: tie points, GCPs, reference
DEM, one block adjustment, parameters :class:`~tiledsm.orient.spec.OrientSpec`)
and the DSM computed from the bias-corrected copies
:func:`orient_for_recipe` writes (RPC tags and a ``_RPC.TXT`` sidecar each,
the input's pixel grid).

Conventions as in :mod:`tiledsm.orient.points` (GDAL pixel coordinates,
WGS84 lon/lat, ellipsoidal heights).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from tiledsm.orient.spec import OrientSpec

__all__ = ["orient_for_recipe", "polygon_exclusion"]


def polygon_exclusion(path: str | Path) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``exclude(lon, lat) -> bool``: inside one of the polygons of a GeoJSON
    file (:func:`tiledsm.compare.stable.read_polygons`: a rupture zone, the
    areas excluded from stable terrain); holes are outside."""
    from matplotlib.path import Path as MplPath

    from tiledsm.compare.stable import read_polygons

    polys = []
    for g in read_polygons(path, "EPSG:4326"):
        for rings in ([g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]):
            polys.append([MplPath(np.asarray(r, float)[:, :2]) for r in rings])

    def exclude(lon, lat) -> np.ndarray:
        pts = np.column_stack([np.ravel(lon), np.ravel(lat)])
        out = np.zeros(len(pts), bool)
        for outer, *holes in polys:
            m = outer.contains_points(pts)
            for h in holes:
                m &= ~h.contains_points(pts)
            out |= m
        return out.reshape(np.shape(lon))

    return exclude


def orient_for_recipe(
    images: Sequence[str | Path],
    rpcs: Sequence[Optional[str]] | None,
    spec: OrientSpec,
    out_dir: str | Path,
    *,
    exclude: Callable | None = None,
    overwrite: bool = False,
) -> tuple[list[str], None, dict]:
    """Orient a recipe's images; return the corrected images to match.

    Parameters
    ----------
    images : sequence of path-like
        The recipe's images (``input.images``).
    rpcs : sequence of (path or None), optional
        The recipe's ``input.rpcs`` (one per image, None: the image's own).
    spec : OrientSpec
    out_dir : path-like
        Where :func:`~tiledsm.orient.stage.write_orientation` writes
        ``<stem>.tif``, ``<stem>_RPC.TXT``, ``orient.json``, residuals.
    exclude : callable, optional
        ``exclude(lon, lat) -> bool``: tie points on unstable ground left
        out (:func:`polygon_exclusion`).
    overwrite : bool
        Orient again even when ``out_dir`` holds the products of the same
        inputs and spec (otherwise they are reused, as DSM chunks are).

    Returns
    -------
    (images, rpcs, report)
        The corrected copies (cameras in their tags: ``rpcs`` is None) and
        the ``orient.json`` document.

    Raises
    ------
    InputFileError, RPCError, InvalidOptionError, MatchingError
        As :func:`~tiledsm.orient.stage.orient_images`.
    """
    from tiledsm.io.cameras import find_camera
    from tiledsm.orient.dem import ReferenceDEM
    from tiledsm.orient.stage import orient_images, write_orientation

    out = Path(out_dir)
    paths = [Path(p) for p in images]
    rpc_files = list(rpcs) if rpcs is not None else [None] * len(paths)
    inputs = {"images": [str(p.resolve()) for p in paths], "rpcs": [str(r) if r else None for r in rpc_files],
              "orient": spec.model_dump(mode="json"), "exclude": exclude is not None}
    corrected = [str(out / (p.stem + ".tif")) for p in paths]
    doc_path = out / "orient.json"
    if not overwrite and doc_path.is_file() and all(Path(c).is_file() for c in corrected):
        doc = json.loads(doc_path.read_text())
        if doc.get("inputs") == inputs:
            return corrected, None, doc
    cams = [find_camera(p, rpc=r)[0] for p, r in zip(paths, rpc_files)]
    dem = None
    if spec.dem:
        import rasterio

        shapes = []
        for p in paths:
            with rasterio.open(p) as ds:
                shapes.append((ds.height, ds.width))
        dem = ReferenceDEM.for_cameras(spec.dem, cams, shapes, geoid=spec.geoid)
    o = orient_images(paths, spec.gcps, spec.check_points, dem, spec, rpcs=cams, exclude=exclude)
    doc = write_orientation(o, out, spec, extra={"inputs": inputs})
    return corrected, None, doc
