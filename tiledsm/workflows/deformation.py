"""Pre/post-event deformation workflow: two stereo pairs -> two DSMs on one
grid -> co-registered difference -> vertical displacement and fault throw.

``pipeline: deformation`` (see :class:`DeformationRecipe`) writes into the
run folder ``OUT``:

- ``pre/`` and ``post/``: the DSM products of each pair (``dsm.zarr``,
  ``dsm.tif``, ``dsm.png``, resumable), the post DSM on **the pre DSM's
  ground grid** (same CRS, transform and shape: no resampling in the
  difference);
- ``compare/``: the products of :func:`tiledsm.compare.compare_dsms`
  (``dh.zarr``, ``dh.tif``, quick-looks, ``report.html``, its
  ``metrics.json``) with ``dh = post_corrected - pre`` (metres);
- ``metrics.json``: the DSM reports, the co-registration found, stable
  terrain statistics, the completeness of ``dh`` and the throw measured
  across the fault trace (when one is known). The errors against a truth
  (the synthetic scene, ``input.truth_dh``) are not the run's:
  ``tiledsm evaluate OUT`` writes them into ``OUT/evaluation.json``
  (:mod:`tiledsm.evaluate.deformation`);
- ``scene/`` (synthetic input): the scene of :func:`tiledsm.synth.make_scene`
  and ``stable_mask.geojson`` (the exclusion polygons written from the known
  event);
- ``displacement/``, ``pre/ortho.*``, ``post/ortho.*`` (with a
  ``displacement:`` section): east/north/up displacement with its
  uncertainty (:mod:`tiledsm.workflows.displacement`);
- ``orient/`` (with an ``orient:`` section, :class:`DeformationOrientSpec`):
  the bias-corrected images the DSMs are computed from and their
  ``orient.json`` (:mod:`tiledsm.orient`). By default pre- and post-event
  images form one block whose tie points are common to both epochs and lie
  on stable ground (outside ``compare.stable_mask``), so both DSMs share
  one frame before they are differenced; ``joint: false`` orients each
  epoch alone (``orient/pre``, ``orient/post``).

Conventions
-----------
Heights and ``dh`` in metres (ellipsoidal for both DSMs, so ``dh`` is
datum-free). The fault trace is oriented: its *right* side (looking along
the trace from its first to its last point) is the block whose ``dh`` minus
the left block's is the reported throw (positive: the right block went up
relative to the left one). For a synthetic event this is the convention of
:class:`tiledsm.synth.EventParams` (strike and right-hand normal).

Throw measure: ``median(dh)`` over valid cells at ``strip[0]..strip[1]``
metres on the right of the trace minus the same on the left (cells closer
than ``strip[0]`` are left out: the matching window smooths the step there).
``tiledsm evaluate`` takes the same measure on the truth ``dh`` over the
same cells for the truth throw, so the error compares like with like.

Reference frame of the truth: co-registration aligns the post DSM on the
terrain declared stable, so ``dh`` is displacement *relative to that
terrain*. When the "stable" terrain itself moved (in the synthetic event
both blocks move by ``+-throw/2`` and ``+-slip/2``: nothing is still), the
truth is expressed in the same frame: the expected co-registration is minus
the median truth displacement ``(dx, dy, dz)`` over the stable cells, and the
truth ``dh`` is ``shift(post_truth, expected) + expected_dz - pre_truth``.
With ``coreg: none`` (or a truly still stable terrain) the expected
co-registration is zero and this is the plain truth ``dh``.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Literal, Optional

import numpy as np
from pydantic import Field, field_validator, model_validator

from tiledsm.compare.recipe import CompareSpec
from tiledsm.errors import NoOverlapError, TiledsmError
from tiledsm.orient.spec import OrientSpec
from tiledsm.recipes import ClusterSpec, GridSpec, MatchSpec, OutputSpec, SynthInput, StrictModel
from tiledsm.workflows.displacement import DisplacementSpec
from tiledsm.workflows.fault import Fault, event_exclusion_polygons, write_geojson

__all__ = ["DeformationRecipe", "fault_from_trace", "plan_deformation", "run_deformation"]

log = logging.getLogger("tiledsm.workflows.deformation")


# --------------------------------------------------------------------------- recipe schema
class PairInput(StrictModel):
    """One stereo pair (or more views) of one epoch: images with RPCs in their
    tags, a sidecar, or ``rpcs`` (one entry per image, ``null`` allowed)."""

    images: list[str] = Field(..., min_length=2)
    rpcs: Optional[list[Optional[str]]] = None

    @model_validator(mode="after")
    def _one_rpc_per_image(self):
        if self.rpcs is not None and len(self.rpcs) != len(self.images):
            raise ValueError("'rpcs' needs one entry per image")
        return self


class EventSynthInput(SynthInput):
    """A synthetic pre/post-event scene (:func:`tiledsm.synth.make_scene`
    with ``event=True``)."""

    event: bool = True
    still: Literal["none", "left"] = Field(
        "none",
        description="'left': the block left of the fault stays still and the right one moves by the full slip and "
        "throw and carries the uplift (the usual real case; the stable terrain is the still block); 'none': both "
        "blocks move by half",
    )
    post_aim_offset: tuple[float, float] = Field(
        (0.0, 0.0), description="metres east/north by which the post-event cameras aim away from the pre-event ones "
        "(another orbit: post pixels sample the ground at another phase; own RPCs)")
    post_bh: Optional[float] = Field(None, gt=0, description="base-to-height ratio of the post pair (another "
                                     "acquisition; default: the pre pair's)")
    auto_stable_mask: bool = Field(
        True,
        description="write stable_mask.geojson from the known event (fault zone, uplift and the block holding "
        "the uplift excluded) when compare.stable_mask is not given",
    )

    @field_validator("event")
    @classmethod
    def _needs_event(cls, value: bool) -> bool:
        if not value:
            raise ValueError("a deformation run needs the post-event scene: event must be true")
        return value


class DeformationInput(StrictModel):
    """Either ``synth`` (known truth) or the ``pre`` and ``post`` pairs."""

    synth: Optional[EventSynthInput] = None
    pre: Optional[PairInput] = None
    post: Optional[PairInput] = None
    truth_dh: Optional[str] = Field(None, description="reference dh raster (post - pre, metres) that tiledsm "
                                    "evaluate scores the run against")
    truth_mask: Optional[str] = Field(None, description="uint8 raster, 1 where truth_dh is evaluated")

    @model_validator(mode="after")
    def _one_source(self):
        pairs = (self.pre is not None, self.post is not None)
        if self.synth is not None and any(pairs):
            raise ValueError("give either 'synth' or the 'pre' and 'post' pairs, not both")
        if self.synth is None and not all(pairs):
            raise ValueError("give 'synth' (a synthetic event) or both 'pre' and 'post' pairs")
        if self.synth is not None and (self.truth_dh or self.truth_mask):
            raise ValueError("'truth_dh'/'truth_mask' come from the synthetic scene; leave them out with 'synth'")
        if self.truth_mask and not self.truth_dh:
            raise ValueError("'truth_mask' needs 'truth_dh'")
        return self


class FaultSpec(StrictModel):
    """Fault trace across which the throw is measured (real inputs; a
    synthetic event knows its own); the strips are ``compare.strip``."""

    trace: list[tuple[float, float]] = Field(
        ..., min_length=2, max_length=2, description="two (lon, lat) points, WGS84 degrees; right side = up is positive"
    )


class DeformationCompareSpec(CompareSpec):
    """``compare:`` of a deformation recipe: the comparison stage's parameters
    (:class:`tiledsm.compare.recipe.CompareSpec`, what
    :func:`~tiledsm.compare.compare_dsms` takes) with a smaller chunk and the
    throw's strips."""

    chunk: int = Field(512, ge=16, description="chunk side of the comparison grid, cells")
    strip: tuple[float, float] = Field((3.0, 20.0), description="throw strips: inner and outer distance to the fault trace, metres")

    @field_validator("strip")
    @classmethod
    def _ordered(cls, value):
        if not 0 <= value[0] < value[1]:
            raise ValueError(f"need 0 <= inner < outer, got {value}")
        return value


class DeformationOrientSpec(OrientSpec):
    """``orient:`` of a deformation recipe (:class:`tiledsm.orient.spec.OrientSpec`
    plus ``joint``). GCP and check-point files name images of both epochs
    when ``joint`` (of one epoch otherwise: give them with ``joint: true``)."""

    joint: bool = Field(
        True,
        description="orient pre- and post-event images together in one block (tie points common to both epochs, "
        "on stable ground: outside compare.stable_mask) so both DSMs share one frame; false: each epoch alone",
    )

    @model_validator(mode="after")
    def _points_need_joint(self):
        if not self.joint and (self.gcps or self.check_points):
            raise ValueError("'gcps'/'check_points' name images of both epochs: use them with 'joint: true'")
        return self


class DeformationRecipe(StrictModel):
    """``pipeline: deformation`` — pre and post pairs to a vertical
    displacement map, co-registered on stable terrain, with the throw."""

    pipeline: Literal["deformation"]
    name: str = "deformation"
    input: DeformationInput
    fault: Optional[FaultSpec] = None
    grid: GridSpec = GridSpec()
    match: MatchSpec = MatchSpec()
    compare: DeformationCompareSpec = DeformationCompareSpec()
    cluster: ClusterSpec = ClusterSpec()
    output: OutputSpec = OutputSpec()
    orient: Optional[DeformationOrientSpec] = None
    displacement: Optional[DisplacementSpec] = Field(
        None, description="also measure the 3D displacement: orthos of both epochs correlated (dE, dN), dU read at the "
        "displaced position, per-cell uncertainty (tiledsm.workflows.displacement)")

    @model_validator(mode="after")
    def _fault_source(self):
        if self.fault is not None and self.input.synth is not None:
            raise ValueError("'fault' is known for a synthetic event; leave it out with 'input.synth'")
        return self




# --------------------------------------------------------------------------- runner
def _grid_lonlat_box(grid) -> tuple[float, float, float, float]:
    from pyproj import Transformer

    left, bottom, right, top = grid.bounds
    tr = Transformer.from_crs(grid.crs, "EPSG:4326", always_xy=True)
    xs = np.array([left, right, left, right, (left + right) / 2, (left + right) / 2, left, right])
    ys = np.array([bottom, bottom, top, top, bottom, top, (bottom + top) / 2, (bottom + top) / 2])
    lon, lat = tr.transform(xs, ys)
    return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))


def _check_post_sees_grid(images, rpcs, h_range, grid, pre_images) -> None:
    """Refuse, before anything is computed, a post pair that sees none of the pre grid."""
    from tiledsm.dsm import open_views
    from tiledsm.geometry.footprint import overlap_lonlat_bounds

    views = open_views(images, rpcs)
    try:
        lon0, lat0, lon1, lat1 = overlap_lonlat_bounds(views[0].rpc, views[0].shape, views[1].rpc, views[1].shape, h_range)
    except NoOverlapError:
        raise NoOverlapError(f"post-event views {', '.join(map(str, images))} have no ground in common") from None
    g0, g1, g2, g3 = _grid_lonlat_box(grid)
    if lon0 >= g2 or lon1 <= g0 or lat0 >= g3 or lat1 <= g1:
        raise NoOverlapError(
            f"post-event views {', '.join(map(str, images))} see no ground of the pre-event DSM grid "
            f"(pre-event views {', '.join(map(str, pre_images))}): post footprint lon/lat "
            f"[{lon0:.5f}, {lat0:.5f}, {lon1:.5f}, {lat1:.5f}], pre grid [{g0:.5f}, {g1:.5f}, {g2:.5f}, {g3:.5f}]"
        )


def fault_from_trace(spec: FaultSpec, crs) -> Fault:
    """The oriented trace of ``fault.trace`` (WGS84 points) in ``crs`` (metres)."""
    from pyproj import Transformer

    (lon0, lat0), (lon1, lat1) = spec.trace
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform([lon0, lon1], [lat0, lat1])
    if math.hypot(x[1] - x[0], y[1] - y[0]) == 0:
        raise TiledsmError(f"fault.trace: the two points {spec.trace} are the same")
    return Fault((x[0], y[0]), (x[1] - x[0], y[1] - y[0]))


def _orient_epochs(spec: DeformationOrientSpec, pre_in, post_in, out: Path, stable_mask, overwrite: bool):
    """Bias-corrected images of both epochs (module notes): ``(pre_in,
    post_in, report)`` with the corrected copies and no separate RPCs."""
    from tiledsm.orient.step import orient_for_recipe, polygon_exclusion

    def rpcs_of(epoch):
        return list(epoch[1]) if epoch[1] is not None else [None] * len(epoch[0])

    if spec.joint:
        exclude = polygon_exclusion(stable_mask) if stable_mask else None
        n = len(pre_in[0])
        images, _, rep = orient_for_recipe([*pre_in[0], *post_in[0]], rpcs_of(pre_in) + rpcs_of(post_in), spec,
                                           out / "orient", exclude=exclude, overwrite=overwrite)
        return (images[:n], None), (images[n:], None), {"joint": True, **_orient_summary(rep)}
    res, reps = [], {"joint": False}
    for name, epoch in (("pre", pre_in), ("post", post_in)):
        images, _, rep = orient_for_recipe(epoch[0], rpcs_of(epoch), spec, out / "orient" / name, overwrite=overwrite)
        res.append((images, None))
        reps[name] = _orient_summary(rep)
    return res[0], res[1], reps


def _orient_summary(rep: dict) -> dict:
    keys = ("n_tracks", "n_tracks_excluded", "tie_relative_rms_px", "gcp_rms_px", "check_rms_px", "rejected_gcps", "dem")
    return {**{k: rep[k] for k in keys if k in rep}, "terms": {Path(d["image"]).name: d["terms"] for d in rep["images"]}}


# --------------------------------------------------------------------------- the DSM of each epoch
def _event_params(sy: EventSynthInput):
    from tiledsm.synth import EventParams

    return EventParams.for_extent(sy.size * sy.gsd, still=sy.still, post_aim_offset=tuple(sy.post_aim_offset),
                                  post_bh=sy.post_bh)


def _epoch_recipe(recipe: DeformationRecipe, epoch: str, images, rpcs, grid: GridSpec):
    """The ``pipeline: dsm`` recipe of one epoch (its own folder ``OUT/<epoch>``)."""
    from tiledsm.workflows.stage_dsm import dsm_recipe

    return dsm_recipe(f"{recipe.name}-{epoch}", images, rpcs, grid, recipe.match, recipe.output, recipe.cluster)


def _rpc_height_range(images, rpcs) -> tuple[float, float]:
    """The heights the pair's cameras are valid for (RPC offset +- scale), metres."""
    from tiledsm.dsm import open_views

    r = open_views(images, rpcs)[0].rpc
    return (r.height_off - r.height_scale, r.height_off + r.height_scale)


def _plan_epochs(recipe: DeformationRecipe, out: Path, pre_in, post_in, pre_grid: GridSpec, cluster,
                 overwrite: bool, limits) -> list[tuple[str, object, object]]:
    """``[(epoch, dsm recipe, plan)]`` of both DSMs, the post one on the pre
    one's grid (a post pair that sees none of it is refused first)."""
    from tiledsm.workflows.stage_dsm import grid_spec, plan_stage_dsm

    pre = _epoch_recipe(recipe, "pre", *pre_in, pre_grid)
    pre_plan = plan_stage_dsm(pre, out / "pre", cluster, overwrite=overwrite, limits=limits)
    grid = pre_plan.prepared.grid
    _check_post_sees_grid(post_in[0], post_in[1], _rpc_height_range(*post_in), grid, pre_in[0])
    post = _epoch_recipe(recipe, "post", *post_in, grid_spec(grid))
    post_plan = plan_stage_dsm(post, out / "post", cluster, overwrite=overwrite, limits=limits)
    epochs = [("pre", pre, pre_plan), ("post", post, post_plan)]
    for _, sub, p in epochs:
        p.recipe = p.recipe or sub  # what the run computes (a reused plan carries it)
    return [(name, p.recipe, p) for name, _, p in epochs]


def plan_deformation(plan, recipe: DeformationRecipe, cluster=None, *, overwrite: bool = False, names=None):
    """Fill ``plan`` (:func:`tiledsm.pipelines.plan_recipe`) for a deformation
    recipe: the recipe's input files, then the DSM stage's plan of each
    epoch into ``OUT/pre`` and ``OUT/post`` (grid, chunks, levels, worker
    memory; :attr:`Plan.stages`). A synthetic event is planned from its
    parameters (:func:`tiledsm.workflows.stage_dsm.plan_unmade_dsm`);
    with ``orient:`` the DSMs are planned on the given images (the run
    plans them again on the corrected ones)."""
    from tiledsm.plan.recipes import check_recipe_inputs
    from tiledsm.workflows.stage_dsm import (
        SYNTH_ITEMSIZE, add_stages, grid_spec, plan_unmade_dsm, scene_heights, synthetic_views,
    )

    check_recipe_inputs(plan, recipe)
    out, inp = plan.out, recipe.input
    if inp.synth is not None:
        from tiledsm.synth.layout import scene_layout

        sy = inp.synth
        lay = scene_layout(sy.size, sy.gsd, sy.bh, sy.seed, sy.views, True, event_params=_event_params(sy))
        scene = out / "scene"
        pre_paths = [scene / f"view_{i}.tif" for i in range(sy.views)]
        post_paths = [scene / f"post_view_{i}.tif" for i in range(sy.views)]
        h_range = scene_heights(lay, recipe.match)
        pre = _epoch_recipe(recipe, "pre", pre_paths, None, recipe.grid)
        pre_plan, grid = plan_unmade_dsm(out / "pre", synthetic_views(lay, lay.cameras, pre_paths), h_range, pre,
                                         itemsize=SYNTH_ITEMSIZE, default_grid=lay.grid, limits=plan.limits)
        post = _epoch_recipe(recipe, "post", post_paths, None, grid_spec(grid))
        post_plan, _ = plan_unmade_dsm(out / "post", synthetic_views(lay, lay.post_cameras, post_paths, first_view=100),
                                       h_range, post, itemsize=SYNTH_ITEMSIZE, limits=plan.limits)
        plan.notes.append(f"synthetic event scene {sy.size}² px at {sy.gsd:g} m is made by the run in {scene}: the "
                          "DSMs are planned from its parameters (truth grid, fitted cameras, terrain heights); their "
                          "heights come from the scene's tie points once it is made")
        stages = [("pre", pre_plan), ("post", post_plan)]
    else:
        epochs = _plan_epochs(recipe, out, (inp.pre.images, inp.pre.rpcs), (inp.post.images, inp.post.rpcs),
                              recipe.grid, cluster, overwrite, plan.limits)
        stages = [(name, p) for name, _, p in epochs]
        if recipe.orient is not None:
            plan.notes.append("orient: the DSMs are planned on the given images; the run plans them again on the "
                              "bias-corrected copies")
    return add_stages(plan, stages, "per DSM (above); compare/ is recomputed from the two DSMs")


# --------------------------------------------------------------------------- runner
def run_deformation(recipe: DeformationRecipe, out: Path, cluster=None, overwrite: bool = False, plan=None) -> dict:
    """Pre and post pairs -> DSMs on one grid -> co-registered ``dh`` -> metrics.

    Each DSM is made by the DSM stage (:mod:`tiledsm.workflows.stage_dsm`:
    planned, memory-fitted, resumable) into ``out/pre`` and ``out/post``;
    ``plan`` (:func:`plan_deformation`) carries both epochs' prepared DSMs
    for given pairs, which are then not prepared twice. Completeness and
    throw are dask reductions. The run scores nothing against a truth:
    ``tiledsm evaluate OUT`` does (:func:`tiledsm.evaluate.deformation.score`).
    See the module notes for the products and conventions.

    Raises
    ------
    NoOverlapError
        The post pair sees none of the pre DSM's grid (checked before any
        DSM is computed), or the DSMs have no valid cell in common.
    NoStableTerrainError
        The exclusion polygons leave no stable terrain for the fit.
    """
    import dask.array as da

    from tiledsm.cluster import compute_context, shared_cluster
    from tiledsm.compare import CompareOutput, compare_dsms
    from tiledsm.io import open_product
    from tiledsm.plan.core import Limits
    from tiledsm.workflows.common import write_json
    from tiledsm.workflows.fault import strips_lazy, throw_of_strips
    from tiledsm.workflows.stage_dsm import run_stage_dsm, stage_report

    out = Path(out)
    cluster = cluster or recipe.cluster.config()
    limits = plan.limits if plan is not None else Limits()
    t_start = time.perf_counter()
    timings: dict = {}
    inp, g = recipe.input, recipe.grid
    scene = None
    pre_grid = g
    if inp.synth is not None:
        from tiledsm.synth import make_scene

        sy = inp.synth
        log.info("making synthetic event scene %s", sy.model_dump())
        t0 = time.perf_counter()
        scene = make_scene(out / "scene", size=sy.size, gsd=sy.gsd, bh=sy.bh, seed=sy.seed, views=sy.views, event=True,
                           event_params=_event_params(sy))
        timings["scene_s"] = time.perf_counter() - t0
        pre_in = ([str(p) for p in scene.views], None)
        post_in = ([str(p) for p in scene.event["post_views"]], None)
        if not (g.like or g.bounds or g.resolution):
            pre_grid = GridSpec(like=str(scene.truth_dsm), chunk=g.chunk)  # truth on the DSM grid, unresampled
    else:
        pre_in = (inp.pre.images, inp.pre.rpcs)
        post_in = (inp.post.images, inp.post.rpcs)

    # ---- stable terrain (before orientation: its tie points must avoid the moved ground)
    stable_mask = recipe.compare.stable_mask
    if scene is not None and stable_mask is None and inp.synth.auto_stable_mask and recipe.compare.coreg != "none":
        feats, _ = event_exclusion_polygons(scene.event["params"], scene.origin, scene.grid.width * scene.grid.resolution)
        stable_mask = str(write_geojson(feats, scene.grid.crs, out / "scene" / "stable_mask.geojson"))
    orient_report = None
    if recipe.orient is not None:
        t0 = time.perf_counter()
        pre_in, post_in, orient_report = _orient_epochs(recipe.orient, pre_in, post_in, out, stable_mask, overwrite)
        timings["orient_s"] = time.perf_counter() - t0

    # ---- both DSMs planned by the DSM stage (the plan's, when it prepared them), the post one on the pre grid
    planned = plan is not None and plan.stages and all(p.prepared is not None for _, p in plan.stages)
    if planned and scene is None and recipe.orient is None:
        epochs = [(name, p.recipe, p) for name, p in plan.stages]
    else:
        epochs = _plan_epochs(recipe, out, pre_in, post_in, pre_grid, cluster, overwrite, limits)
    grid = epochs[0][2].prepared.grid
    reports = {name: p.prepared.report for name, _, p in epochs}

    # ---- fault
    fault, strip = None, recipe.compare.strip
    if scene is not None:
        ev = scene.event["params"]
        fault = Fault(np.asarray(ev.fault_point) + np.asarray(scene.origin), ev.strike)
    elif recipe.fault is not None:
        fault = fault_from_trace(recipe.fault, grid.crs)
    compare_spec = recipe.compare.model_copy(update={"stable_mask": stable_mask})  # the synthetic event's own mask
    compare_output = CompareOutput(cog=recipe.output.cog, quicklook=recipe.output.quicklook)

    # ---- compute, on one cluster for the three stages
    dsm_metrics = {}
    with shared_cluster(cluster) as run_cluster:
        for name, sub, p in epochs:
            log.info("%s-event DSM into %s", name, out / name)
            t0 = time.perf_counter()
            dsm_metrics[name] = run_stage_dsm(p, sub, out / name, run_cluster, overwrite=overwrite)
            timings[f"dsm_{name}_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        with compute_context(run_cluster):
            res = compare_dsms(out / "pre" / "dsm.zarr", out / "post" / "dsm.zarr", out / "compare", compare_spec,
                               compare_output)
        timings["compare_s"] = time.perf_counter() - t0

        # ---- metrics: dask reductions and the strips' cells; the grid never comes to this process
        cm = res.metrics
        metrics: dict = {
            "pipeline": "deformation",
            "dh_definition": "post_corrected - pre (m)",
            "grid": reports["pre"]["grid"],
            **{name: {"report": reports[name], "dsm": stage_report(dsm_metrics[name])} for name in reports},
            "coregistration": cm["coregistration"],
            "stable_terrain": {**cm["stable_terrain"], "statistics": cm["statistics"]["stable"]},
            "dh_statistics": cm["statistics"]["all"],
            "products": {k: str(Path(v).relative_to(out)) for k, v in res.products.items()},
        }
        if orient_report is not None:
            metrics["orient"] = orient_report
        t0 = time.perf_counter()
        with compute_context(run_cluster):
            dh = open_product(out / "compare" / "dh.zarr")["dh"]
            metrics["completeness"] = float(da.isfinite(dh.data).mean().compute())
            if fault is not None:
                measured = throw_of_strips(*strips_lazy(dh, fault, strip), strip)
                metrics["fault"] = {**fault.to_dict(), "strip_m": list(strip), "measured": measured}
                if scene is not None:
                    metrics["fault"]["nominal_throw"] = float(scene.event["params"].throw)
        timings["metrics_s"] = time.perf_counter() - t0
    if recipe.displacement is not None:
        from tiledsm.workflows.displacement import run_displacement

        t0 = time.perf_counter()
        with shared_cluster(cluster) as run_cluster:
            metrics["displacement"] = run_displacement(
                recipe.displacement, out, pre_images=pre_in[0], post_images=post_in[0], stable_mask=stable_mask,
                fault=fault, cluster=run_cluster, cog=recipe.output.cog,
                quicklook=recipe.output.quicklook)
        timings["displacement_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    metrics["timings"] = timings
    write_json(metrics, out / "metrics.json")
    log.info("metrics: %s", json.dumps(metrics, default=float))
    return metrics
