"""The DSM of views on a ground grid: the coarse-to-fine graph of every
level (:func:`dsm_from_views`, on :mod:`tiledsm.dsm.stages`), its
fingerprint, and the pair shortcut."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import xarray as xr

from tiledsm.errors import MatchingError
from tiledsm.geometry.grid import GroundGrid
from tiledsm.dsm.params import DSMParams
from tiledsm.dsm.layout import level_layout
from tiledsm.dsm.levels import auto_levels, level_geometry
from tiledsm.dsm.stages import ScratchFolder, finest_from_stage, stage_level
from tiledsm.dsm.views import View, default_grid, open_views, scene_height_range

log = logging.getLogger(__name__)


def dsm_from_views(
    views: Sequence[View],
    grid: GroundGrid,
    h_range: tuple[float, float],
    params: DSMParams = DSMParams(),
    stage_dir: str | Path | None = None,
) -> xr.Dataset:
    """Lazy DSM of ``views`` on ``grid`` (coarse to fine).

    Each pyramid level is matched chunk by chunk (a chunk plus its halo,
    :class:`~tiledsm.dsm.layout.LevelLayout`) into a resumable store in
    ``stage_dir``, searching around the coarser level's stored heights; the
    DSM's chunks read the finest store and remove its speckles
    (:mod:`tiledsm.dsm.stages`). Every halo is derived from the parameters,
    so the result does not depend on the chunking, and a task waits only
    for the tasks that write what it reads.

    ``stage_dir`` must be reachable from every worker; the stores of an
    interrupted run there are resumed. Without it the stores go to a
    temporary folder, removed when the returned dataset's graph is gone
    (the same engine). Nothing is written before the graph is computed.

    Returns
    -------
    xarray.Dataset
        ``height`` (float32 metres, WGS84 ellipsoidal, NaN = no height) and
        ``confidence`` (0..1), dims ``(y, x)``, dask-backed, CRS written.
    """
    import rioxarray  # noqa: F401  (registers .rio)

    if h_range[1] <= h_range[0]:
        raise MatchingError(f"empty height range {h_range}")
    levels = params.levels or auto_levels(views, grid, h_range, params)
    fp = dsm_fingerprint(views, grid, h_range, levels, params)
    scratch = ScratchFolder() if stage_dir is None else None
    # absolute: the workers of a remote cluster need not share the client's working directory
    where = scratch.path if scratch is not None else Path(stage_dir).absolute()
    staged = None
    for level in range(levels - 1, -1, -1):
        geom = level_geometry(views, grid, level, h_range, params, levels)
        staged = stage_level(views, geom, level_layout(geom, grid.chunk, params), h_range, params, staged, where,
                             json.dumps(fp, sort_keys=True), keep=scratch)
    arr = finest_from_stage(staged, grid.chunks)
    # the finest level is on `grid` itself; its chunks are the grid's
    ds = xr.Dataset(
        {
            "height": (("y", "x"), arr[0]),
            "confidence": (("y", "x"), arr[1]),
        },
        coords={"y": grid.y, "x": grid.x},
    )
    ds["height"].attrs.update(units="m", long_name="height above the WGS84 ellipsoid", _FillValue=np.nan)
    ds["confidence"].attrs.update(units="1", long_name="matching confidence")
    ds = ds.rio.write_crs(grid.crs).rio.write_transform(grid.transform)
    ds.attrs.update(
        views=[v.path for v in views], height_range_m=list(h_range), levels=levels, params=_params_dict(params),
        fingerprint=json.dumps(fp, sort_keys=True),
    )
    return ds


def dsm_fingerprint(views: Sequence[View], grid: GroundGrid, h_range, levels: int, params: DSMParams) -> dict:
    """Everything that determines the DSM, as plain JSON
    (:func:`tiledsm.provenance.fingerprint`): each input's identity (path,
    size, sampled content hash), the RPCs actually used (after relative
    correction), the grid, height range, levels, every parameter, and the
    package version and code. A stored DSM is resumed only under the same
    fingerprint."""
    from tiledsm.provenance import fingerprint, input_identity

    return fingerprint(
        inputs=[input_identity(v.path) for v in views],
        rpcs=[v.rpc for v in views],
        grid={"crs": str(grid.crs), "x0": grid.x0, "y0": grid.y0, "resolution": grid.resolution,
              "width": grid.width, "height": grid.height, "chunk": grid.chunk},
        height_range=list(h_range),
        levels=levels,
        params=params.model_dump(),
    )


def _params_dict(params: DSMParams) -> str:
    import json

    return json.dumps(params.model_dump())


def prepare_views(views: Sequence[View], params: DSMParams) -> tuple[tuple[float, float], list[View], dict]:
    """Height range, relatively corrected views and report of a DSM run,
    before its graph is built.

    Tie points give the range unless ``params.height_range`` is set; the
    relative correction of views 2.. is applied when
    ``params.relative_correction`` (with a given range a failure of the tie
    points is only logged: a given range is often the answer to it, and the
    tie points' own range is reported as ``tiepoint_height_range_m``).

    Returns
    -------
    (hmin, hmax), views, report
        Ellipsoidal metres; the views as matched; tie points, correction and
        ``preparation_s``.
    """
    t0 = time.perf_counter()
    if params.height_range is None:
        h_range, views, report = scene_height_range(views, params)
    else:
        h_range, report = tuple(params.height_range), {"height_range_m": list(params.height_range)}
        if params.relative_correction:
            try:
                _, views, tie_report = scene_height_range(views, params)
                report.update({k: v for k, v in tie_report.items() if k != "height_range_m"})
                report["tiepoint_height_range_m"] = tie_report["height_range_m"]
            except MatchingError as exc:
                log.warning("no relative correction: %s", exc)
                report["relative_correction"] = f"not applied: {exc}"
    report["preparation_s"] = time.perf_counter() - t0
    return (float(h_range[0]), float(h_range[1])), list(views), report


def dsm_from_pair(
    left: str | Path,
    right: str | Path,
    *more: str | Path,
    rpcs: Sequence[str | Path | None] | None = None,
    grid: GroundGrid | None = None,
    params: DSMParams = DSMParams(),
    stage_dir: str | Path | None = None,
) -> tuple[xr.Dataset, dict]:
    """DSM of two (or more) images with RPCs; lazy.

    ``rpcs`` optionally gives each image's RPC file (``None`` entries: the
    camera is found in the image or a sidecar); ``stage_dir`` is passed to
    :func:`dsm_from_views`. Returns the lazy dataset of
    :func:`dsm_from_views` and a report (tie points, height range, relative
    correction, grid).
    """
    views = open_views([left, right, *more], rpcs)
    h_range, views, report = prepare_views(views, params)
    if grid is None:
        grid = default_grid(views, h_range, params)
    report["grid"] = {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height, "chunk": grid.chunk}
    return dsm_from_views(views, grid, h_range, params, stage_dir=stage_dir), report
