"""``pipeline: displace`` (and ``tiledsm displace PRE POST``): the
horizontal displacement field between two orthoimages of any grid.

PRE and POST are orthoimages (GeoTIFF/COG or tiledsm ortho ``.zarr``
stores) in any projected CRS, cell size or origin, or images with their
cameras and a DSM each (``dsm_pre``, ``dsm_post``), orthorectified first
on their own epoch's DSM (:func:`tiledsm.ortho.stage.ortho_files`, as the
deformation recipe does). The plan
(:func:`plan_displace`) reads their headers, refuses what cannot work
(missing, unreadable or non-georeferenced input, no common ground, bad
options) and states the grid both are read onto
(:func:`tiledsm.displace.grid.displacement_grid`: PRE's own lattice by
default). The run writes into ``OUT``:

- ``pre/ortho.zarr``, ``post/ortho.zarr``: both orthos on that grid (and
  ``pre/ortho_on_dsm.zarr``, ``post/ortho_on_dsm.zarr``: an image given
  with a DSM, orthorectified on that DSM's grid);
- ``displacement.zarr``: ``dE``, ``dN`` (metres east/north, post minus
  pre; NaN where unknown), ``sigma_dE``, ``sigma_dN`` (metres),
  ``quality`` (phase coherence), ``peak`` (phase-correlation peak),
  ``status`` (uint8: 0 measured, 1 no data, 2 no texture, 3 decorrelated:
  a changed surface, cloud or moved shadow -- the correlation's quality,
  peak or residual refused it; never interpolated);
- with both ``dsm_pre`` and ``dsm_post``: ``dU`` (metres up, the post DSM
  read at the displaced position minus the pre DSM,
  :mod:`tiledsm.displace.vertical`; with a stable mask its plane on
  stable terrain removed), ``sigma_dU`` (binned by slope and quality, plus
  the horizontal error along the slope) and ``slope``;
- ``dE.tif``, ``dN.tif``, ``sigma_dE.tif``, ``sigma_dN.tif`` (and
  ``dU.tif``, ``sigma_dU.tif``) (COGs), ``displacement.png`` (arrows over
  PRE, and dU or the displacement's length) and, with a fault trace,
  ``profiles.png``;
- ``metrics.json``, ``recipe.resolved.yaml``, ``run.log``.

Frame: with a stable mask (polygons of moving ground to exclude), a plane
(or the median) fitted on the remaining cells is removed from each
component and the per-cell sigma is calibrated there (binned by the
correlation's formal errors, :mod:`tiledsm.displace.uncertainty`, as the
deformation recipe does). Without one, nothing is removed (the frame is
the two grids' own) and the sigma is the correlation's formal error,
uncalibrated (``metrics.json`` says which).

Large offsets: ``max_displacement`` (metres) beyond ``search`` pixels
runs the correlation coarse to fine (:mod:`tiledsm.displace.pyramid`).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field

from tiledsm.ortho.recipe import KernelName, OrthoSpec
from tiledsm.recipes import ClusterSpec, OutputSpec, StrictModel, option
from tiledsm.workflows.displacement import CorrelationSpec

__all__ = ["DisplaceRecipe", "plan_displace", "run_displace"]

log = logging.getLogger("tiledsm.workflows.displace")

#: the components measured: dU only when both epochs have a DSM
COMPONENTS = ("dE", "dN", "dU")

class DisplaceInput(StrictModel):
    pre: str = Field(..., description="pre-event orthoimage: GeoTIFF/COG or tiledsm ortho .zarr, projected CRS; or, "
                     "with dsm_pre, an image with its camera (RPC tags or sidecar)", json_schema_extra=option('PRE'))
    post: str = Field(..., description="post-event orthoimage: any projected CRS, cell size or origin; or, with "
                      "dsm_post, an image with its camera", json_schema_extra=option('POST'))
    dsm_pre: Optional[str] = Field(None, description="DSM of the pre epoch: pre is orthorectified on it first "
                                   "(tiledsm.ortho, occlusion-aware)", json_schema_extra=option('--dsm-pre'))
    dsm_post: Optional[str] = Field(None, description="DSM of the post epoch: post is orthorectified on it first", json_schema_extra=option('--dsm-post'))
    kernel: KernelName = Field("cs", description="ortho interpolation kernel of images given with a DSM: nn, bl, cr, cs", json_schema_extra=option('--kernel'))


class DisplaceGrid(StrictModel):
    like: Optional[str] = Field(None, description="measure on this raster's lattice (CRS, cell size, origin); "
                                "default: PRE's own", json_schema_extra=option('--like'))
    resolution: Optional[float] = Field(None, gt=0, description="cell size, metres, in PRE's CRS and origin", json_schema_extra=option('--resolution'))
    chunk: int = Field(1024, ge=64, description="ortho pixels per chunk side", json_schema_extra=option('--chunk'))


class DisplaceRecipe(StrictModel):
    """``pipeline: displace``: two orthoimages to a displacement field."""

    pipeline: Literal["displace"]
    name: str = "displace"
    input: DisplaceInput
    grid: DisplaceGrid = DisplaceGrid()
    displacement: CorrelationSpec = CorrelationSpec()
    stable_mask: Optional[str] = Field(None, description="GeoJSON polygons EXCLUDED from stable terrain (moving "
                                       "ground); the rest fixes the frame and calibrates sigma", json_schema_extra=option('--stable-mask'))
    fault_trace: Optional[list[tuple[float, float]]] = Field(
        None, min_length=2, max_length=2, description="two (lon, lat) points, WGS84 degrees: offsets and profiles "
        "across it, right side (looking from the first point to the second) minus left", json_schema_extra=option('--fault-trace'))
    cluster: ClusterSpec = ClusterSpec()
    output: OutputSpec = OutputSpec()


# --------------------------------------------------------------------------- plan
#: how messages name the recipe's fields (the command passes its options instead)
FIELD_NAMES = {"input.pre": "input.pre", "input.post": "input.post", "grid.like": "grid.like",
               "stable_mask": "stable_mask", "fault_trace": "fault_trace", "input.dsm_pre": "input.dsm_pre",
               "input.dsm_post": "input.dsm_post"}


def _lazy_ortho(recipe: DisplaceRecipe, key: str, names: dict):
    """The lazy ortho of ``input.<key>`` on ``input.dsm_<key>`` (None without a DSM)."""
    from tiledsm.ortho.stage import ortho_files
    from tiledsm.plan.core import existing_file, readable_raster

    dsm = getattr(recipe.input, f"dsm_{key}")
    if dsm is None:
        return None
    image = readable_raster(existing_file(getattr(recipe.input, key), names[f"input.{key}"]), names[f"input.{key}"])
    dsm = existing_file(dsm, names[f"input.dsm_{key}"])
    if not dsm.endswith(".zarr"):
        readable_raster(dsm, names[f"input.dsm_{key}"])
    ortho = ortho_files(image, dsm, OrthoSpec(kernel=recipe.input.kernel), chunk=min(recipe.grid.chunk, 512))
    return ortho.rename("ortho")


def _header_of(ortho) -> dict:
    t, shape = ortho.rio.transform(), ortho.rio.shape
    return {"crs": ortho.rio.crs.to_wkt(), "crs_name": ortho.rio.crs.to_string(), "transform": tuple(t)[:6],
            "shape": tuple(shape), "bounds": (t.c, t.f + shape[0] * t.e, t.c + shape[1] * t.a, t.f),
            "res": (t.a, -t.e)}


def displace_grid(recipe: DisplaceRecipe, names: dict | None = None):
    """The grid of a displace run, its inputs' descriptions (for the plan)
    and the lazy orthos of the images given with a DSM: PRE and POST (and
    ``grid.like``) exist, read, are georeferenced (or have a camera and a
    DSM) and overlap by a window."""
    from tiledsm.displace.grid import displacement_grid, ortho_header
    from tiledsm.plan.core import InputInfo, existing_file, readable_raster

    names = {**FIELD_NAMES, **(names or {})}
    heads, infos, orthos = {}, [], {}
    for key in ("pre", "post"):
        role = names[f"input.{key}"]
        orthos[key] = ortho = _lazy_ortho(recipe, key, names)
        if ortho is not None:
            heads[key] = h = _header_of(ortho)
            infos.append(InputInfo(role, str(Path(getattr(recipe.input, key)).resolve()),
                                   f"image, orthorectified on {names[f'input.dsm_{key}']} "
                                   f"{getattr(recipe.input, f'dsm_{key}')}: {h['shape'][0]} x {h['shape'][1]} cells "
                                   f"of {h['res'][0]:g} m, {h['crs_name']} (kernel {recipe.input.kernel})"))
            continue
        path = existing_file(getattr(recipe.input, key), role)
        if not Path(path).is_dir():
            readable_raster(path, role)
        heads[key] = h = ortho_header(path, role)
        infos.append(InputInfo(role, path, f"{h['shape'][0]} x {h['shape'][1]} cells of {h['res'][0]:g} m, "
                                           f"{h['crs_name']}"))
    like = None
    if recipe.grid.like:
        lp = existing_file(recipe.grid.like, names["grid.like"])
        like = ortho_header(lp, names["grid.like"])
        infos.append(InputInfo(names["grid.like"], lp, f"{like['shape'][0]} x {like['shape'][1]} cells"))
    grid = displacement_grid(heads["pre"], heads["post"], like=like, resolution=recipe.grid.resolution,
                             names=(names["input.pre"], names["input.post"]), min_side=recipe.displacement.window)
    return grid, infos, orthos


def plan_displace(recipe: DisplaceRecipe, out, cluster=None, *, overwrite: bool = False, names=None):
    """The plan of a displace run (module notes): inputs, the grid and its
    origin, the pyramid, what an earlier run in ``out`` leaves.

    ``names`` maps recipe fields to how the user spelled them (command
    options); default: the field paths.

    Raises
    ------
    InputFileError, GridError, NoOverlapError, InvalidOptionError
    """
    from tiledsm.plan.core import InputInfo, check_earlier_run, existing_file, new_plan

    names = {**FIELD_NAMES, **(names or {})}
    plan = new_plan("displace", out, cluster)
    grid, infos, orthos = displace_grid(recipe, names)
    plan.inputs.extend(infos)
    spec = recipe.displacement
    params = spec.correlation(grid.resolution)
    plan.grid = grid.text()
    cells = (grid.shape[0] // spec.step, grid.shape[1] // spec.step)
    reach = params.reach * grid.resolution
    plan.notes.append(
        f"field: {cells[0]} x {cells[1]} cells every {spec.step} px ({spec.step * grid.resolution:g} m), windows of "
        f"{spec.window} px ({spec.window * grid.resolution:g} m)")
    if params.levels:
        plan.notes.append(
            f"coarse to fine: {params.levels} coarse level(s) (x{params.factor}), search {spec.search} px there: reach "
            f"{params.reach} px ({reach:g} m) >= max_displacement {spec.max_displacement:g} m; full resolution "
            f"searches {spec.refine_search} px around the coarse candidates")
    else:
        plan.notes.append(f"one level: search {spec.search} px ({reach:g} m) around zero; a larger offset is NaN "
                          "(give --max-displacement METRES)")
    if recipe.stable_mask:
        mask = existing_file(recipe.stable_mask, names["stable_mask"])
        plan.inputs.append(InputInfo(names["stable_mask"], mask))
        from tiledsm.compare.stable import read_polygons
        from tiledsm.errors import NoOverlapError
        from tiledsm.plan.recipes import polygons_touch

        if not polygons_touch(read_polygons(mask, grid.crs), grid.bounds):
            raise NoOverlapError(f"{mask}: {names['stable_mask']}: no polygon lies within the grid {grid.bounds}: it "
                                 "would exclude nothing")
    else:
        plan.notes.append("no stable mask: no frame correction; sigma = the correlation's formal error (uncalibrated)")
    if recipe.fault_trace is not None:
        fault_on_grid(recipe.fault_trace, grid.crs, names["fault_trace"])
    plan.reuse = "nothing: the field is recomputed whole"
    check_earlier_run(recipe, plan.out, overwrite)
    plan.product = (grid, orthos)
    return plan


def fault_on_grid(trace, crs: str, name: str = "fault_trace"):
    """The :class:`~tiledsm.workflows.fault.Fault` of two (lon, lat) points in ``crs``."""
    from pyproj import Transformer

    from tiledsm.errors import InvalidOptionError
    from tiledsm.workflows.fault import Fault

    (lon0, lat0), (lon1, lat1) = trace
    if not all(-180 <= lo <= 180 and -90 <= la <= 90 for lo, la in trace):
        raise InvalidOptionError(f"{name}: (lon, lat) degrees expected, got {list(trace)}")
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform([lon0, lon1], [lat0, lat1])
    if math.hypot(x[1] - x[0], y[1] - y[0]) == 0:
        raise InvalidOptionError(f"{name}: the two points {list(trace)} are the same")
    return Fault((x[0], y[0]), (x[1] - x[0], y[1] - y[0]))


# --------------------------------------------------------------------------- run
def run_displace(recipe: DisplaceRecipe, out: Path, cluster=None, overwrite: bool = False, plan=None) -> dict:
    """Two orthos -> the displacement products and metrics (module notes)."""
    import xarray as xr

    from tiledsm.cluster import compute_context, compute_with_progress
    from tiledsm.compare.stable import exclusion_mask, read_polygons
    from tiledsm.displace import correlate_orthos
    from tiledsm.displace.correct import CorrectionParams, correct_component
    from tiledsm.displace.grid import read_on_grid
    from tiledsm.displace.masks import STATUS, cell_status
    from tiledsm.displace.trace import locate_trace
    from tiledsm.displace.uncertainty import Variogram, binned_sigma, fit_variogram
    from tiledsm.io import open_product, withdraw, write_cog, write_zarr
    from tiledsm.workflows.common import write_json
    from tiledsm.workflows.displacement import fault_section
    from tiledsm.workflows.fault import error_stats

    cluster = cluster or recipe.cluster.config()
    # `tiledsm run` plans recipes generically: the grid is derived here then (same checks, same messages)
    grid, orthos = (plan.product if plan is not None and plan.product is not None else displace_grid(recipe)[::2])
    warnings = list(plan.warnings) if plan is not None else []
    spec = recipe.displacement
    res = grid.resolution
    params = spec.correlation(res)
    withdraw(out, ["displacement.png", "profiles.png", *[f"{p}{c}.tif" for p in ("", "sigma_") for c in COMPONENTS],
                   "displacement.zarr"])
    timings: dict = {}
    log.info("grid: %s", grid.text())

    # ---- both orthos on the grid (stores: each correlation task then reads its own window)
    t0 = time.perf_counter()
    stores = {}
    with compute_context(cluster) as client:
        for key in ("pre", "post"):
            source = getattr(recipe.input, key)
            if orthos[key] is not None:  # an image with a DSM: its ortho first, on the DSM's grid
                source = write_zarr(orthos[key], out / key / "ortho_on_dsm.zarr",
                                    compute=lambda d: compute_with_progress(d, config=cluster, client=client))
                log.info("%s ortho of %s on %s: %s", key, getattr(recipe.input, key),
                         getattr(recipe.input, f"dsm_{key}"), source)
            arr = read_on_grid(str(source), grid, recipe.grid.chunk)
            t = grid.affine()
            da_ = xr.DataArray(arr, dims=("y", "x"), name="ortho",
                               coords={"y": t.f + (np.arange(grid.shape[0]) + 0.5) * t.e,
                                       "x": t.c + (np.arange(grid.shape[1]) + 0.5) * t.a})
            da_ = da_.rio.write_crs(grid.crs).rio.write_transform(t)
            stores[key] = write_zarr(da_, out / key / "ortho.zarr",
                                     compute=lambda d: compute_with_progress(d, config=cluster, client=client))
    timings["orthos_s"] = time.perf_counter() - t0

    # ---- the field
    t0 = time.perf_counter()
    field = correlate_orthos(stores["pre"], stores["post"], params, chunk=recipe.grid.chunk)
    layers = ("dE", "dN", "quality", "texture", "peak", "formal_dE", "formal_dN")
    with compute_context(cluster) as client:
        (raw,) = compute_with_progress(xr.concat([field[v] for v in layers], "band").data, config=cluster,
                                       client=client)
    f = {n: np.asarray(raw[i], np.float64) for i, n in enumerate(layers)}
    timings["correlation_s"] = time.perf_counter() - t0
    x, y = field.x.values, field.y.values
    transform, crs = field.rio.transform(), field.rio.crs
    shape = f["dE"].shape
    pre_px = np.asarray(open_product(stores["pre"]).values, np.float32)
    post_px = np.asarray(open_product(stores["post"]).values, np.float32)
    status = cell_status(f, pre_px, post_px, spec.step, spec.min_texture)

    # ---- frame and sigma: on stable terrain when a mask says where it is
    fields, corrections = {}, {}
    if recipe.stable_mask:
        stable = ~exclusion_mask(read_polygons(recipe.stable_mask, crs), transform, shape)
        cp = CorrectionParams(plane=spec.plane, stripes=spec.stripes)
        for n in ("dE", "dN"):
            fields[n], corrections[n] = correct_component(f[n], x, y, stable, cp, n)
        sigma_kind = "binned by the formal errors, calibrated on stable terrain"
    else:
        stable = np.ones(shape, bool)
        fields = {"dE": f["dE"], "dN": f["dN"]}
        sigma_kind = "formal error of the correlation (no stable terrain given: uncalibrated)"
    # ---- vertical: both epochs' DSMs given, dU read at the displaced position (as the deformation recipe does)
    slope = None
    if recipe.input.dsm_pre and recipe.input.dsm_post:
        t0 = time.perf_counter()
        du, slope = _vertical(recipe, grid, fields, spec, res, cluster)
        if recipe.stable_mask:  # the epochs' DSMs' vertical offset and tilt, fitted on stable terrain
            fields["dU"], corrections["dU"] = correct_component(du, x, y, stable, cp, "dU")
        else:
            fields["dU"] = du
        timings["vertical_s"] = time.perf_counter() - t0
    names = list(fields)
    sigmas, tables, varios = {}, {}, {}
    for n in names:
        if not recipe.stable_mask:
            # no stable terrain: the correlation's formal error (dU: none, NaN); no residual to fit a spatial
            # correlation on, taken as uncorrelated (metrics say both)
            formal = f.get(f"formal_{n}", np.full(shape, np.nan))
            sigmas[n], tables[n] = np.where(np.isfinite(fields[n]), formal, np.nan), {}
            varios[n] = Variogram(1.0, 0.0, spec.step * res)
            continue
        preds = {"formal": f[f"formal_{n}"]} if n != "dU" else {"slope": slope, "quality": f["quality"]}
        sigmas[n], tables[n] = binned_sigma(fields[n], stable, preds)
        if n == "dU":  # dU is read at p + d: the horizontal error moves the reading along the slope
            sigmas[n] = np.hypot(sigmas[n], np.tan(np.radians(slope)) * np.hypot(sigmas["dE"], sigmas["dN"]))
        z = fields[n] / sigmas[n]
        varios[n], _ = fit_variogram(z, x, y, stable & np.isfinite(z))

    # ---- products
    ds = xr.Dataset(
        {**{n: (("y", "x"), fields[n].astype(np.float32)) for n in names},
         **{f"sigma_{n}": (("y", "x"), sigmas[n].astype(np.float32)) for n in names},
         "quality": (("y", "x"), f["quality"].astype(np.float32)), "peak": (("y", "x"), f["peak"].astype(np.float32)),
         "status": (("y", "x"), status)},
        coords={"y": y, "x": x},
    ).rio.write_crs(crs).rio.write_transform(transform)
    if slope is not None:
        ds["slope"] = (("y", "x"), slope.astype(np.float32))
        ds["slope"].attrs.update(units="degree", long_name="median slope of the pre DSM in the cell")
    for n, long in (("dE", "east"), ("dN", "north"), ("dU", "up"))[:len(names)]:
        ds[n].attrs.update(units="m", long_name=f"{long} displacement (post - pre)")
        ds[f"sigma_{n}"].attrs.update(units="m", long_name=f"standard error of {n} ({sigma_kind})")
    ds["status"].attrs.update(long_name="why a cell is NaN", codes=str(STATUS))
    ds.attrs.update({f"correlation_{k}": v for k, v in vars(params).items()})
    write_zarr(ds.chunk({"y": 1024, "x": 1024}), out / "displacement.zarr")
    stored = open_product(out / "displacement.zarr")
    if recipe.output.cog:
        for n in (*names, *[f"sigma_{c}" for c in names]):
            write_cog(stored[n], out / f"{n}.tif")

    valid = np.isfinite(fields["dE"])
    metrics: dict = {
        "grid": {"text": grid.text(), "crs": crs.to_string(), "transform": list(grid.transform),
                 "shape": list(grid.shape), "resolution_m": res, "field_shape": list(shape),
                 "field_cell_m": spec.step * res},
        "correlation": {k: v for k, v in vars(params).items() if k != "batch"},
        "reach_m": params.reach * res,
        "resolution_limit_m": spec.window * res,
        "valid_share": float(valid.mean()),
        "status_share": {k: float((status == v).mean()) for k, v in STATUS.items()},
        "frame": {"corrected": bool(recipe.stable_mask), "correction": corrections},
        "sigma": sigma_kind,
        "stable_cells": int((stable & valid).sum()),
        "stable_noise": {n: {**error_stats(fields[n][stable & np.isfinite(fields[n])]),
                             "nmad_px": float(error_stats(fields[n][stable & np.isfinite(fields[n])])["nmad"] / res)}
                         for n in names} if recipe.stable_mask else None,
        "uncertainty": {n: {"bins": tables[n], "variogram": varios[n].to_dict()} for n in names},
        "warnings": warnings,
    }
    fault = None
    if recipe.fault_trace is not None:
        fault = fault_on_grid(recipe.fault_trace, grid.crs)
        distance = fault.signed_distance(x, y)
        sec = fault_section(fields, sigmas, varios, fault, distance, x, y, spec.window, spec.step, res)
        sec["trace_location"] = locate_trace(fields, distance, sec["offsets"], fault, 3 * spec.window * res, res)
        metrics["fault"] = {**fault.to_dict(), **sec}
    if recipe.output.quicklook:
        _figures(fields, ds, pre_px, fault, metrics, out)
    metrics["timings"] = timings
    metrics["products"] = sorted(p.name for p in out.iterdir() if p.name not in ("run.log", ".lock"))
    write_json(metrics, out / "metrics.json")
    return metrics


def _figures(fields: dict, ds, pre_px: np.ndarray, fault, metrics: dict, out: Path) -> None:
    from tiledsm.displace.figures import displacement_figure, profile_figure

    t = ds.rio.transform()
    ny, nx = fields["dE"].shape
    extent = (t.c, t.c + nx * t.a, t.f + ny * t.e, t.f)
    k = max(1, int(max(pre_px.shape) // 1024))
    img = pre_px[::k, ::k]
    lo, hi = np.nanpercentile(img, [1, 99]) if np.isfinite(img).any() else (0.0, 1.0)
    shade = np.clip((np.nan_to_num(img, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1)
    # the PRE pixels span the field's cells and the crop past the last whole cell
    extent_img = (t.c, t.c + pre_px.shape[1] * t.a / _step(ds), t.f + pre_px.shape[0] * t.e / _step(ds), t.f)
    line = None
    if fault is not None:
        L = 2 * max(extent[1] - extent[0], extent[3] - extent[2])
        p, s = fault.point, fault.strike
        line = (np.array([p[0] - L * s[0], p[0] + L * s[0]]), np.array([p[1] - L * s[1], p[1] + L * s[1]]))
    displacement_figure(fields["dE"], fields["dN"], fields.get("dU"), extent, out / "displacement.png", shade=shade,
                        shade_extent=extent_img, title="horizontal displacement (post - pre) over PRE",
                        fault_line=line)
    if "fault" in metrics:
        profile_figure(metrics["fault"]["profiles"], metrics["fault"]["offsets"], out / "profiles.png",
                       title="across the fault trace")


def _vertical(recipe, grid, fields: dict, spec, res: float, cluster):
    """``(dU, slope)`` on the field grid: both DSMs read onto the grid, the
    post one at each cell's ``p + d`` (:func:`tiledsm.displace.vertical.vertical_displacement`)."""
    import dask.array as da

    from tiledsm.cluster import compute_context, compute_with_progress
    from tiledsm.displace.grid import read_on_grid
    from tiledsm.displace.vertical import vertical_displacement

    pre_h, post_h = (read_on_grid(p, grid, recipe.grid.chunk) for p in (recipe.input.dsm_pre, recipe.input.dsm_post))
    fchunk = max(1, recipe.grid.chunk // spec.step)
    dE, dN = (da.from_array(np.nan_to_num(fields[n], nan=0.0), chunks=fchunk) for n in ("dE", "dN"))
    vd = vertical_displacement(pre_h, post_h, dE, dN, step=spec.step, res=res)
    with compute_context(cluster) as client:
        (vert,) = compute_with_progress(vd, config=cluster, client=client)
    du = np.where(np.isfinite(fields["dE"]) & np.isfinite(fields["dN"]), vert[0], np.nan).astype(np.float64)
    return du, np.asarray(vert[1], np.float64)


def _step(ds) -> int:
    return int(ds.attrs["correlation_step"])
