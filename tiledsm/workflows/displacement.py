"""3D displacement of a deformation run: orthoimages of both epochs,
their sub-pixel correlation, the frame correction on stable terrain,
``dU`` read at the displaced position, per-cell uncertainty and offsets
across the fault. The errors against a truth are not the run's:
``tiledsm evaluate OUT`` scores the finished folder
(:mod:`tiledsm.evaluate.displacement`).

Run by :func:`tiledsm.workflows.deformation.run_deformation` when the
recipe has a ``displacement:`` section (:class:`DisplacementSpec`), after
both DSMs and ``dh``. Products (run folder ``OUT``):

- ``pre/ortho.*``, ``post/ortho.*``: the first image of each pair
  orthorectified on its own epoch's DSM (the cameras the DSM matched with);
- ``displacement/displacement.zarr`` with ``dE``, ``dN``, ``dU``,
  ``sigma_dE``, ``sigma_dN``, ``sigma_dU`` (metres east/north/up, NaN where
  unknown), ``quality`` and ``slope``; the COGs ``dE.tif`` ... ``sigma_dU.tif``;
  ``displacement.png`` (arrows over hillshade, ``dU``) and, with a fault,
  ``profiles.png``.

Frame: the correlation measures the post ortho against the pre ortho; a
plane (and optional row stripes) fitted on the stable terrain is removed
(:mod:`tiledsm.displace.correct`), so ``dE``/``dN`` are relative to that
terrain, like ``dh`` after co-registration. ``dU = post_c(p + d) - pre(p)``
with ``post_c = pre + dh`` the co-registered post DSM
(:mod:`tiledsm.displace.vertical`).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field, field_validator

from tiledsm.ortho.recipe import KernelName, OrthoSpec
from tiledsm.recipes import StrictModel, option

__all__ = ["DisplacementSpec", "run_displacement"]

log = logging.getLogger("tiledsm.workflows.displacement")

COMPONENTS = ("dE", "dN", "dU")


class CorrelationSpec(StrictModel):
    """The correlation options a displacement shares, in the recipe
    (``displacement:`` of ``deformation``, ``displace``) and on the
    command line (pixels of the ortho grid)."""

    window: int = Field(32, ge=8, description="correlation window side, pixels (even)", json_schema_extra=option('--window'))
    step: int = Field(8, ge=2, description="spacing of the displacement cells, pixels (even; <= window/2)", json_schema_extra=option('--step'))
    search: int = Field(8, ge=1, description="largest displacement looked for, pixels per axis (at the coarsest "
                        "level when max_displacement asks for a pyramid)", json_schema_extra=option('--search'))
    frequency_cut: float = Field(0.6, gt=0, le=1, description="share of Nyquist used by the sub-pixel phase fit")
    min_quality: float = Field(0.5, ge=0, le=1, description="phase coherence under which a cell is NaN", json_schema_extra=option('--min-quality'))
    min_peak: float = Field(0.15, ge=0, le=1, description="coarse phase-correlation peak under which a cell is NaN "
                            "(no true match within search)", json_schema_extra=option('--min-peak'))
    min_texture: float = Field(1.0, ge=0, description="std of the pre window (DN) under which a cell is NaN", json_schema_extra=option('--min-texture'))
    plane: bool = Field(True, description="remove a plane per component fitted on stable terrain (else its median)")
    stripes: Optional[Literal["rows"]] = Field(None, description="also remove along-row stripes (attitude jitter)", json_schema_extra=option('--stripes'))
    max_displacement: Optional[float] = Field(
        None, gt=0, description="largest displacement expected, metres: beyond search pixels, the correlation runs "
        "coarse to fine (tiledsm.displace.pyramid) with search at the coarsest level; default: search pixels", json_schema_extra=option('--max-displacement'))
    refine_search: int = Field(4, ge=1, description="with a pyramid: search around each coarse candidate at full "
                               "resolution, pixels", json_schema_extra=option('--refine-search'))

    @field_validator("window", "step")
    @classmethod
    def _even(cls, value: int, info) -> int:
        if value % 2:
            raise ValueError(f"an even number of pixels, got {value}")
        if info.field_name == "step" and value > info.data.get("window", value):
            raise ValueError(f"at most the window ({info.data['window']} px), got {value}")
        return value

    def levels(self, res: float) -> int:
        """Coarse levels that make ``search`` at the coarsest reach
        ``max_displacement`` (``res``: metres per ortho pixel)."""
        if self.max_displacement is None:
            return 0
        need = self.max_displacement / res
        return 0 if need <= self.search else int(math.ceil(math.log2(need / self.search)))

    def correlation(self, res: float | None = None):
        from tiledsm.displace import CorrelationParams

        return CorrelationParams(window=self.window, step=self.step, search=self.search,
                                 frequency_cut=self.frequency_cut, min_quality=self.min_quality,
                                 min_peak=self.min_peak, min_texture=self.min_texture,
                                 levels=0 if res is None else self.levels(res), refine_search=self.refine_search)


class DisplacementSpec(CorrelationSpec):
    """``displacement:`` of a deformation recipe (pixels of the ortho grid,
    which is the DSM grid)."""

    kernel: KernelName = Field("cs", description="ortho interpolation kernel: nn, bl, cr, cs")
    view: int = Field(0, ge=0, description="which image of each pair is orthorectified (index in the pair)")
    chunk: int = Field(1024, ge=64, description="ortho pixels per chunk side for the correlation")


def _orthos(spec: DisplacementSpec, pre_image: str, post_image: str, out: Path, cluster, cog: bool, quicklook: bool):
    """Both orthos, each on its own epoch's DSM store; returns their zarr stores."""
    from tiledsm.ortho.rectify import orthorectify
    from tiledsm.ortho.stage import open_dsm, open_source, write_ortho_products

    reports = {}
    for name, image in (("pre", pre_image), ("post", post_image)):
        dsm = out / name / "dsm.zarr"
        ortho = orthorectify(open_source(image, dsm=dsm), open_dsm(dsm), OrthoSpec(kernel=spec.kernel))
        reports[name] = write_ortho_products(ortho, out / name, cluster=cluster, cog=cog, quicklook=quicklook)
        log.info("%s-event ortho of %s: %.1f %% valid", name, image, 100 * reports[name].get("valid_share", np.nan))
    return out / "pre" / "ortho.zarr", out / "post" / "ortho.zarr", reports


def _strip_cells(distance: np.ndarray, strip: tuple[float, float], valid: np.ndarray):
    a = np.abs(distance)
    band = valid & (a >= strip[0]) & (a <= strip[1])
    return band & (distance > 0), band & (distance < 0)


def _offsets(fields: dict, sigmas: dict, varios: dict, fault, distance, x, y, strip) -> dict:
    """Offset of each component across the fault (median right strip minus
    median left strip) with its standard error (:func:`mean_error` of both)."""
    from tiledsm.displace.uncertainty import mean_error

    out = {}
    for name, v in fields.items():
        right, left = _strip_cells(distance, strip, np.isfinite(v) & np.isfinite(sigmas[name]))
        if not right.any() or not left.any():
            continue
        e = np.hypot(mean_error(sigmas[name], x, y, right, varios[name]),
                     mean_error(sigmas[name], x, y, left, varios[name]))
        out[name] = {"offset": float(np.median(v[right]) - np.median(v[left])), "error": float(1.2533 * e),
                     "cells": [int(left.sum()), int(right.sum())]}
    return out


def _profiles(fields: dict, distance: np.ndarray, half_width: float, bin_m: float) -> dict:
    edges = np.arange(-half_width, half_width + bin_m, bin_m)
    k = np.digitize(distance, edges) - 1
    prof = {"distance_m": ((edges[:-1] + edges[1:]) / 2).tolist()}
    for name, v in fields.items():
        vals = []
        for b in range(len(edges) - 1):
            m = (k == b) & np.isfinite(v)
            vals.append(float(np.median(v[m])) if m.sum() >= 3 else float("nan"))
        prof[name] = vals
    return prof


def fault_section(fields: dict, sigmas: dict, varios: dict, fault, distance: np.ndarray, x, y, window: int,
                  step: int, res: float) -> dict:
    """Offsets across the fault (along and across strike, and ``dU`` when
    ``fields`` has it) with their errors, and binned profiles; strips from
    ``window / 2 + step`` (cells whose window straddles the trace left out)
    to ``max(30 m, 2 windows)`` beyond (``res``: metres per ortho pixel)."""
    inner = 0.5 * window * res + step * res
    strip = (inner, inner + max(30.0, 2 * window * res))
    s, nrm = fault.strike, fault.normal
    comp = {"along_strike": fields["dE"] * s[0] + fields["dN"] * s[1],
            "across_strike": fields["dE"] * nrm[0] + fields["dN"] * nrm[1]}
    csig = {"along_strike": np.hypot(sigmas["dE"] * s[0], sigmas["dN"] * s[1]),
            "across_strike": np.hypot(sigmas["dE"] * nrm[0], sigmas["dN"] * nrm[1])}
    cvar = {"along_strike": varios["dE"], "across_strike": varios["dE"]}
    if "dU" in fields:
        comp["dU"], csig["dU"], cvar["dU"] = fields["dU"], sigmas["dU"], varios["dU"]
    offsets = _offsets(comp, csig, cvar, fault, distance, x, y, strip)
    profiles = _profiles(comp, distance, strip[1] + 10, 2 * step * res)
    return {"strip_m": list(strip), "offsets": offsets, "profiles": profiles}


def run_displacement(spec: DisplacementSpec, out: Path, *, pre_images, post_images, stable_mask, fault,
                     cluster, cog: bool = True, quicklook: bool = True) -> dict:
    """The 3D displacement step (module notes); returns its metrics.

    Raises
    ------
    GridError
        The two orthos are not on one grid.
    NoStableCellsError
        No correlated cell is left on the stable terrain.
    """
    import xarray as xr

    from tiledsm.cluster import compute_context, compute_with_progress
    from tiledsm.compare.stable import exclusion_mask, read_polygons
    from tiledsm.displace import correlate_orthos
    from tiledsm.displace.correct import CorrectionParams, correct_component
    from tiledsm.displace.uncertainty import binned_sigma, fit_variogram
    from tiledsm.displace.vertical import vertical_displacement
    from tiledsm.io import open_product, withdraw, write_cog, write_zarr
    from tiledsm.workflows.fault import error_stats

    if spec.view >= min(len(pre_images), len(post_images)):
        from tiledsm.errors import RecipeError

        raise RecipeError(f"displacement.view: {spec.view} is past the images of a pair ({len(pre_images)})")
    params = spec.correlation()
    dout = out / "displacement"
    dout.mkdir(parents=True, exist_ok=True)
    withdraw(dout, ["displacement.png", "profiles.png", *[f"{n}.tif" for n in COMPONENTS],
                    *[f"sigma_{n}.tif" for n in COMPONENTS]])
    timings = {}
    t0 = time.perf_counter()
    pre_o, post_o, ortho_reports = _orthos(spec, pre_images[spec.view], post_images[spec.view], out, cluster, cog,
                                           quicklook)
    timings["orthos_s"] = time.perf_counter() - t0
    # the pyramid's levels need the ortho's cell size (max_displacement is in metres)
    params = spec.correlation(abs(float(open_product(pre_o).rio.transform().a)))

    # ---- horizontal field (small: the ortho grid coarsened step times)
    t0 = time.perf_counter()
    # from the stores: each task reads its own window (memory does not grow with the scene)
    field = correlate_orthos(pre_o, post_o, params, chunk=spec.chunk)
    with compute_context(cluster) as client:
        layers = ("dE", "dN", "quality", "formal_dE", "formal_dN")
        (raw,) = compute_with_progress(xr.concat([field[v] for v in layers], "band").data, config=cluster,
                                       client=client)
    dE_raw, dN_raw, quality, formal_dE, formal_dN = (np.asarray(raw[i], np.float64) for i in range(len(layers)))
    timings["correlation_s"] = time.perf_counter() - t0
    x, y = field.x.values, field.y.values
    transform, crs = field.rio.transform(), field.rio.crs
    res = abs(float(field.rio.transform().a)) / spec.step
    shape = dE_raw.shape

    # ---- stable terrain on the field grid, frame correction
    stable = np.ones(shape, bool)
    if stable_mask:
        stable = ~exclusion_mask(read_polygons(stable_mask, crs), transform, shape)
    cp = CorrectionParams(plane=spec.plane, stripes=spec.stripes)
    dE, rep_e = correct_component(dE_raw, x, y, stable, cp, "dE")
    dN, rep_n = correct_component(dN_raw, x, y, stable, cp, "dN")

    # ---- vertical, read at the displaced position
    t0 = time.perf_counter()
    import dask.array as da

    pre_h = open_product(out / "pre" / "dsm.zarr")["height"].data
    dh = open_product(out / "compare" / "dh.zarr")["dh"].data
    post_c = pre_h.astype(np.float32) + dh.astype(np.float32)
    fchunk = max(1, spec.chunk // spec.step)
    vd = vertical_displacement(pre_h, post_c, da.from_array(np.nan_to_num(dE, nan=0.0), chunks=fchunk),
                               da.from_array(np.nan_to_num(dN, nan=0.0), chunks=fchunk), step=spec.step, res=res)
    with compute_context(cluster) as client:
        (vert,) = compute_with_progress(vd, config=cluster, client=client)
    dU = np.where(np.isfinite(dE) & np.isfinite(dN), vert[0], np.nan).astype(np.float64)
    slope = np.asarray(vert[1], np.float64)
    timings["vertical_s"] = time.perf_counter() - t0

    # ---- uncertainty: heteroscedastic (binned) and spatially correlated (variogram)
    fields = {"dE": dE, "dN": dN, "dU": dU}
    # dE/dN binned by the correlation's formal standard errors (the phase-plane fit's own precision),
    # calibrated on stable terrain: the moving block's larger errors show in its fits' residuals, not in the
    # still ground's statistics. Measured on the synthetic event (benchmarks/displacement.py), within 2 sigma:
    # dE / dN 0.890 / 0.928 binned by phase coherence, 0.904 / 0.933 by the formal errors (dU 0.901 either
    # way; binned by slope and the formal errors instead of quality: 0.902); slope as a further predictor of
    # dE made it worse (0.869)
    preds = {"dE": {"formal": formal_dE}, "dN": {"formal": formal_dN},
             "dU": {"slope": slope, "quality": quality}}
    sigmas, tables, varios, vario_docs = {}, {}, {}, {}
    for name, v in fields.items():
        sigmas[name], tables[name] = binned_sigma(v, stable, preds[name])
        if name == "dU":
            # dU is read at p + d: the horizontal error moves the reading along the slope
            sigmas[name] = np.hypot(sigmas[name], np.tan(np.radians(slope)) * np.hypot(sigmas["dE"], sigmas["dN"]))
        z = v / sigmas[name]
        varios[name], emp = fit_variogram(z, x, y, stable & np.isfinite(z))
        vario_docs[name] = {**varios[name].to_dict(), "empirical": emp}

    # ---- products
    ds = xr.Dataset(
        {**{n: (("y", "x"), fields[n].astype(np.float32)) for n in COMPONENTS},
         **{f"sigma_{n}": (("y", "x"), sigmas[n].astype(np.float32)) for n in COMPONENTS},
         "quality": (("y", "x"), quality.astype(np.float32)), "slope": (("y", "x"), slope.astype(np.float32))},
        coords={"y": y, "x": x},
    ).rio.write_crs(crs).rio.write_transform(transform)
    for n, long in (("dE", "east"), ("dN", "north"), ("dU", "up")):
        ds[n].attrs.update(units="m", long_name=f"{long} displacement (post - pre), stable-terrain frame")
        ds[f"sigma_{n}"].attrs.update(units="m", long_name=f"standard error of {n}")
    ds.attrs.update({f"correlation_{k}": v for k, v in vars(params).items()})
    write_zarr(ds.chunk({"y": 1024, "x": 1024}), dout / "displacement.zarr")
    stored = open_product(dout / "displacement.zarr")
    if cog:
        for n in (*COMPONENTS, *[f"sigma_{c}" for c in COMPONENTS]):
            write_cog(stored[n], dout / f"{n}.tif")

    metrics: dict = {
        "grid": {"shape": list(shape), "resolution_m": float(abs(transform.a)), "step_px": spec.step},
        "correlation": {k: v for k, v in vars(params).items() if k != "batch"},
        "resolution_limit_m": spec.window * res,
        "aliasing_safe": spec.step <= spec.window // 2,
        "orthos": {k: {kk: r.get(kk) for kk in ("image", "valid_share", "kernel")} for k, r in ortho_reports.items()},
        "valid_share": float(np.isfinite(dE).mean()),
        "correction": {"dE": rep_e, "dN": rep_n},
        "stable_cells": int((stable & np.isfinite(dE)).sum()),
        "stable_noise": {n: {**error_stats(fields[n][stable & np.isfinite(fields[n])]),
                             "nmad_px": float(error_stats(fields[n][stable & np.isfinite(fields[n])])["nmad"] / res)}
                         for n in COMPONENTS},
        "uncertainty": {n: {"bins": tables[n], "variogram": vario_docs[n]} for n in COMPONENTS},
    }

    # ---- fault offsets and profiles
    distance = None
    if fault is not None:
        distance = fault.signed_distance(x, y)
        metrics["fault"] = fault_section(fields, sigmas, varios, fault, distance, x, y, spec.window, spec.step, res)

    if quicklook:
        _figures(ds, fields, stable, fault, metrics, out, dout)
    metrics["timings"] = timings
    metrics["products"] = {p.name: str(p.relative_to(out)) for p in sorted(dout.iterdir())}
    return metrics


def _figures(ds, fields, stable, fault, metrics, out: Path, dout: Path) -> None:
    from tiledsm.displace.figures import displacement_figure, profile_figure
    from tiledsm.io import open_product
    from tiledsm.quicklook import hillshade

    t = ds.rio.transform()
    ny, nx = fields["dE"].shape
    extent = (t.c, t.c + nx * t.a, t.f + ny * t.e, t.f)
    pre = open_product(out / "pre" / "dsm.zarr")["height"]
    k = max(1, int(max(pre.shape) // 1024))
    z = np.asarray(pre.data[::k, ::k].compute(), np.float64)
    res = abs(float(pre.rio.transform().a)) * k
    shade = hillshade(np.nan_to_num(z, nan=float(np.nanmedian(z))), res)
    line = None
    if fault is not None:
        L = 2 * max(extent[1] - extent[0], extent[3] - extent[2])
        p, s = fault.point, fault.strike
        line = (np.array([p[0] - L * s[0], p[0] + L * s[0]]), np.array([p[1] - L * s[1], p[1] + L * s[1]]))
    displacement_figure(fields["dE"], fields["dN"], fields["dU"], extent, dout / "displacement.png", shade=shade,
                        title="3D displacement (post - pre), stable-terrain frame", fault_line=line)
    if "fault" in metrics:
        profile_figure(metrics["fault"]["profiles"], metrics["fault"]["offsets"], dout / "profiles.png",
                       title="across the fault trace")
