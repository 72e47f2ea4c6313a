"""The plan of a DSM run: inputs, grid, height range, levels, reuse."""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path
from typing import Sequence

from tiledsm.errors import (
    GridError,
    InvalidOptionError,
    MatchingError,
    NoOverlapError,
    TiledsmError,
)
from tiledsm.cluster import tasks_per_device, worker_memory_budget
from tiledsm.plan.core import (
    MOSTLY_OUTSIDE,
    RECIPE_NAMES,
    FieldNames,
    InputInfo,
    Limits,
    Plan,
    PreparedDSM,
    existing_file,
    format_bounds,
    overlap_fraction,
    raster_header,
    readable_raster,
    refuse_or_warn,
    seen_fraction,
)
from tiledsm.dsm.memory import dsm_levels


# --------------------------------------------------------------------------- DSM
def _explicit_grid(spec, names: FieldNames, like: str | None):
    """The grid a recipe's ``grid`` section names (``like`` or ``bounds``)
    and the option to blame for it, or ``(None, resolution option)``."""
    from tiledsm.geometry.grid import GroundGrid
    from tiledsm.io.grids import grid_like

    if like:
        try:
            return grid_like(like, chunk=spec.chunk), f"{names.like} {like}"
        except TiledsmError as exc:
            raise type(exc)(f"{names.like}: {exc}") from None
    if spec.bounds:
        return GroundGrid.from_bounds(spec.crs, spec.bounds, spec.resolution, chunk=spec.chunk), names.bounds
    return None, names.resolution


@contextlib.contextmanager
def _naming(images: Sequence[str]):
    """Matching failures of the scene as a whole (no tie points, no
    parallax, heights outside the RPCs' range) name its images."""
    try:
        yield
    except MatchingError as exc:
        if any(str(i) in str(exc) for i in images):
            raise
        raise type(exc)(f"{', '.join(map(str, images))}: {exc}") from None


def _check_crs(crs: str, name: str) -> None:
    """Refuse a CRS that pyproj does not know, naming the option."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        CRS.from_user_input(crs)
    except CRSError as exc:
        raise InvalidOptionError(f"{name} {crs}: not a known CRS ({exc})") from None


def _check_geoid_covers(geoid: str, grid, name: str) -> None:
    """Refuse a geoid grid that has no undulation at the DSM grid's corners
    and centre (a regional grid of another area)."""
    import numpy as np

    from tiledsm.geometry.footprint import to_lonlat
    from tiledsm.io.geoid import geoid_height

    x = np.array([grid.x[0], grid.x[-1], grid.x[0], grid.x[-1], grid.x[len(grid.x) // 2]])
    y = np.array([grid.y[0], grid.y[0], grid.y[-1], grid.y[-1], grid.y[len(grid.y) // 2]])
    lon, lat = to_lonlat(grid.crs, x, y)
    if not np.isfinite(geoid_height(lon, lat, geoid)).all():
        raise InvalidOptionError(
            f"{geoid}: {name}: the geoid grid does not cover the DSM grid (lon {lon.min():.4f}..{lon.max():.4f}, "
            f"lat {lat.min():.4f}..{lat.max():.4f})"
        )


def grid_text(grid) -> str:
    nby, nbx = grid.numblocks
    return (f"{grid.crs}, {grid.resolution:g} m cells, {grid.height} x {grid.width} cells "
            f"({grid.height * grid.width / 1e6:.3g} Mcells), chunks of {grid.chunk}: {nby} x {nbx} = {nby * nbx}, "
            f"bounds {format_bounds(grid.bounds)}")


def _check_grid_size(grid, limits: Limits, what: str, names: FieldNames) -> None:
    nby, nbx = grid.numblocks
    limits.check(
        grid.width * grid.height, nby * nbx,
        f"{what}: the DSM grid would be {grid.height:,} x {grid.width:,} cells of {grid.resolution:g} m",
        f"choose a coarser {names.resolution}, a smaller grid ({names.bounds}) or a larger {names.chunk}",
    )


def dsm_reuse(out: Path, grid, fingerprint: dict, overwrite: bool) -> tuple[str, bool]:
    """What of ``out/dsm.zarr`` (finished) or ``out/dsm.zarr.partial`` a
    run would reuse, and whether its products will change (``withdraw``).

    Raises
    ------
    FingerprintMismatchError
        The stored DSM was computed from other inputs or parameters and
        not ``overwrite`` (the message the run itself would give).
    """
    from tiledsm.io import ChunkStore
    from tiledsm.plan.core import store_reuse

    store = ChunkStore(str(out / "dsm.zarr"), ("height", "confidence"), grid.shape, (grid.chunk, grid.chunk))
    return store_reuse(store, "DSM", fingerprint, overwrite)


def plan_dsm(plan: Plan, recipe, cluster=None, *, overwrite: bool = False, names: FieldNames = RECIPE_NAMES) -> Plan:
    """Fill ``plan`` (made by :func:`tiledsm.pipelines.plan_recipe`) for a ``pipeline: dsm``
    recipe (``tiledsm dsm`` builds one).

    Checks, in this order, each failure one line naming the option or
    field: the input files exist; the views and cameras open; the
    parameters are valid; an explicit grid (``like``/``bounds``) is within
    ``plan.limits``; then tie points give the height range and relative
    correction (a few seconds); a given height range meets them; the
    default grid is within the limits; the grid is seen by the images; the
    reference covers the grid; the lazy graph is built and counted; the
    earlier run in ``plan.out``, if any, can be resumed. A synthetic input
    (``input.synth``) is made by the run, so its plan stops at the inputs.

    Returns
    -------
    Plan
        ``plan``, with :attr:`Plan.prepared` for the run (None for
        synthetic input).
    """
    from tiledsm.dsm import DSMParams, dsm_from_views, heights_above_geoid, open_views
    from tiledsm.dsm.stages import LEVELS_DIR

    out, limits = plan.out, plan.limits
    inp, spec = recipe.input, recipe.grid
    if inp.synth is not None:
        plan.notes.append(f"synthetic scene {inp.synth.size}² px at {inp.synth.gsd} m is made by the run in "
                          f"{out / 'scene'}; its grid, graph and memory are planned then")
        plan.reuse = "decided once the scene is made: a DSM store in the folder is resumed if its fingerprint matches"
        return plan
    orient = getattr(recipe, "orient", None)
    for key in ("gcps", "check_points", "dem", "geoid"):  # the orientation runs first: its files are inputs too
        if orient is not None and getattr(orient, key):
            plan.inputs.append(InputInfo(f"orient.{key}", existing_file(getattr(orient, key), f"orient.{key}")))
    images = [readable_raster(existing_file(p, names.images), names.images) for p in inp.images]
    rpcs = [None if r is None else existing_file(r, names.rpcs) for r in inp.rpcs] if inp.rpcs else None
    reference = existing_file(inp.reference, names.reference) if inp.reference else None
    like = existing_file(spec.like, names.like) if spec.like else None
    geoid = existing_file(recipe.output.geoid, names.geoid) if recipe.output.geoid else None
    views = open_views(images, rpcs)
    for v in views:
        source = (v.rpc.source or "?").replace(v.path, "").strip(" ()") or v.rpc.source
        plan.inputs.append(InputInfo(names.images, v.path, f"{v.shape[0]} x {v.shape[1]} px, camera: {source}"))
    params = DSMParams.of_recipe(recipe.grid, recipe.match)  # the recipe's models checked every value, naming its field
    if spec.crs:
        _check_crs(spec.crs, names.crs)
    if params.height_range is not None and not params.height_range[0] < params.height_range[1]:
        raise InvalidOptionError(f"{names.height_range}: HMIN must be below HMAX, got {list(params.height_range)}")
    grid, what = _explicit_grid(spec, names, like)
    if like:
        plan.inputs.append(InputInfo(names.like, like, f"its grid: {grid.height} x {grid.width} cells, {grid.crs}"))
    if grid is not None:
        _check_grid_size(grid, limits, what, names)
    from tiledsm.dsm import prepare_views

    with _naming(images):
        h_range, views, report = prepare_views(views, params)
    plan.height_range = h_range
    if "tiepoint_height_range_m" in report:
        _check_given_range(plan, h_range, report["tiepoint_height_range_m"], names.height_range)
    if grid is None:
        from tiledsm.dsm import default_grid

        with _naming(images):
            grid = default_grid(views, h_range, params)
        what = f"{names.resolution} {grid.resolution:g}" if spec.resolution else "the default grid"
        _check_grid_size(grid, limits, what, names)
    report["grid"] = {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height,
                      "chunk": grid.chunk}
    plan.grid = grid_text(grid)
    _check_resolution(plan, grid, views, h_range, what if like else f"{names.resolution} {grid.resolution:g}")
    _check_seen(plan, grid, views, h_range, what)
    if reference:
        _check_reference(plan, reference, grid, names.reference)
    if geoid:
        _check_geoid_covers(geoid, grid, names.geoid)
        plan.inputs.append(InputInfo(names.geoid, geoid))

    def build(grid, params):
        with _naming(images):
            ds = dsm_from_views(views, grid, h_range, params, stage_dir=out / LEVELS_DIR)
        if geoid:
            ds = heights_above_geoid(ds, geoid)
            report["vertical_datum"] = ds.attrs["vertical_datum"]
        plan.tasks = len(ds.__dask_graph__())
        plan.levels, plan.memory = dsm_levels(views, grid, h_range, int(ds.attrs["levels"]), params)
        return ds

    ds = build(grid, params)
    # a worker's memory, then the GPU's share of a task: the default chunk
    # shrinks until both fit (a smaller chunk needs less of each)
    for budget in (_WorkerBudget(worker_memory_budget(cluster)), _GPUBudget.of(params.match.device, cluster)):
        if budget.bytes is None or budget.need(plan.memory) <= budget.bytes:
            continue
        chunk = _chunk_for_budget(plan, views, grid, h_range, int(ds.attrs["levels"]), params, budget,
                                  "chunk" in spec.model_fields_set, names)
        grid, params = dataclasses.replace(grid, chunk=chunk), params.model_copy(update={"chunk": chunk})
        report["grid"]["chunk"] = chunk
        plan.grid = grid_text(grid)
        ds = build(grid, params)
        plan.recipe = recipe.model_copy(update={"grid": spec.model_copy(update={"chunk": chunk})})
    plan.reuse, plan.withdraw = dsm_reuse(out, grid, json.loads(ds.attrs["fingerprint"]), overwrite)
    coarse = ", ".join(f"L{level}" for level in range(int(ds.attrs["levels"]) - 1, 0, -1))
    if coarse:
        plan.notes.append(
            f"coarse levels ({coarse}) are stored in {out / LEVELS_DIR} while the run lasts "
            "(finer tasks read their windows from there; kept for a resume, removed with the finished DSM)"
        )
    plan.prepared = PreparedDSM(images, rpcs, reference, views, grid, h_range, ds, report)
    return plan


def _check_given_range(plan: Plan, given: tuple[float, float], tie: Sequence[float], name: str) -> None:
    """Refuse a given height range that misses the tie points' heights
    (every cell would be NaN); warn when it covers less than half of them."""
    common = min(given[1], tie[1]) - max(given[0], tie[0])
    text = f"{name} {given[0]:g} {given[1]:g}: the tie points lie at {tie[0]:.1f} .. {tie[1]:.1f} m (margin included)"
    if common <= 0:
        raise MatchingError(f"{text}, outside the given range: every cell would be NaN")
    if common < 0.5 * (tie[1] - tie[0]):
        plan.warn(f"{text}; the given range covers {common / (tie[1] - tie[0]):.0%} of them")


#: a DSM cell finer than this fraction of the images' GSD draws a warning
FINEST_OF_GSD = 0.2


def _check_resolution(plan: Plan, grid, views, h_range, what: str) -> None:
    """Warn when the cells are finer than :data:`FINEST_OF_GSD` of the
    images' GSD: the DSM cannot show more than the images do, and costs
    the square of the ratio in cells, memory and time."""
    from tiledsm.dsm.views import mean_gsd

    gsd = mean_gsd(views, float(sum(h_range) / 2))
    if grid.resolution < FINEST_OF_GSD * gsd:
        plan.warn(
            f"{what}: cells of {grid.resolution:g} m are finer than a fifth of the images' GSD ({gsd:g} m): the DSM "
            f"cannot resolve more than the images show, and has {(gsd / grid.resolution) ** 2:,.0f} times the cells "
            f"(and time) of one at the GSD"
        )


def _check_seen(plan: Plan, grid, views, h_range, what: str) -> None:
    """Refuse a grid no view sees; warn when most of it is unseen."""
    frac = seen_fraction(grid, views, float(sum(h_range) / 2))
    plan.notes.append(f"{frac:.0%} of the grid's cells are seen by every view")
    refuse_or_warn(
        plan, frac,
        GridError(f"{what}: the DSM grid {format_bounds(grid.bounds)} ({grid.crs}) lies outside what the images see "
                  f"(no sampled cell projects into every view); the DSM would be empty"),
        f"{what}: the grid is mostly outside the images: only {frac:.0%} of its cells are seen by every view",
    )


def _check_reference(plan: Plan, path: str, grid, name: str) -> None:
    """Refuse a reference raster without CRS or outside the grid; warn when
    it covers little of it."""
    head = raster_header(path, name)
    if head["crs"] is None:
        raise GridError(f"{path}: {name}: has no CRS, so it cannot be compared with the DSM grid")
    frac = overlap_fraction(head["bounds"], head["crs"], grid)
    plan.inputs.append(InputInfo(name, path, f"{head['shape'][0]} x {head['shape'][1]} cells, {head['crs']}, "
                                             f"covers {frac:.0%} of the grid"))
    refuse_or_warn(
        plan, frac,
        NoOverlapError(f"{path}: {name}: covers none of the DSM grid (reference bounds {format_bounds(head['bounds'])} "
                       f"in {head['crs']}, grid bounds {format_bounds(grid.bounds)} in {grid.crs})"),
        f"{path}: {name}: covers only {frac:.0%} of the DSM grid",
    )


#: chunk sides tried, in order, when the default chunk does not fit a worker's memory
_SMALLER_CHUNKS = (384, 256, 192, 128, 96, 64)

#: share of a GPU's free memory the plan gives to the matching tasks that
#: run on it at once (the rest is left to the allocator's rounding and to
#: the kernels' small buffers, which the estimate leaves out)
GPU_USABLE = 0.8


@dataclasses.dataclass(frozen=True)
class _WorkerBudget:
    """A worker's memory: what a task's estimate must fit."""

    bytes: int | None
    what = "a worker would need"
    whose = "a worker's memory"
    beyond = "its memory"
    remedy = "fewer workers, or more memory per worker (--memory-per-worker / cluster.memory_per_worker)"

    @staticmethod
    def need(memory) -> int:
        return memory.total


@dataclasses.dataclass(frozen=True)
class _GPUBudget(_WorkerBudget):
    """A task's share of the GPU it matches on."""

    what = "a task would need on the GPU"
    remedy = "fewer workers (--workers), or a GPU with more free memory"
    tasks: int = 1
    device: str = "cuda"

    @property
    def whose(self) -> str:
        return f"a task's share of the free memory of GPU {self.device} ({self.tasks} tasks at once)"

    @property
    def beyond(self) -> str:
        return f"its share of the free memory of GPU {self.device} ({self.tasks} tasks at once)"

    @staticmethod
    def need(memory) -> int:
        return memory.device

    @classmethod
    def of(cls, device: str, cluster) -> _GPUBudget:
        """The budget of one task on ``device`` (none off a GPU, where the
        tasks per GPU are not known: an existing cluster, or where its
        memory is not: numba's CUDA simulator)."""
        tasks = tasks_per_device(cluster) if str(device).startswith("cuda") else None
        if tasks is None:
            return cls(None)
        from tiledsm.match.cuda_kernel import device_indices, memory_info

        # several GPUs: the threads take them in turn, so each has its share
        gpus = len(device_indices(device))
        tasks = -(-tasks // gpus)
        info = memory_info(device)
        if info is None:
            return cls(None)
        return cls(int(GPU_USABLE * info[0] / tasks), tasks=tasks, device=str(device))


def _chunk_for_budget(plan: Plan, views, grid, h_range, levels: int, params, budget: _WorkerBudget,
                      explicit: bool, names: FieldNames) -> int:
    """The largest chunk side whose estimate fits ``budget`` (a worker's
    memory, or a task's share of a GPU), when the chunk was not given
    (``explicit``); an error naming the chunk option otherwise, or when no
    chunk fits."""
    from dask.utils import format_bytes

    from tiledsm.dsm import min_chunk

    need = budget.need(plan.memory)
    if explicit:
        raise InvalidOptionError(
            f"{names.chunk} {grid.chunk}: {budget.what} ~{format_bytes(need)} (estimated), beyond "
            f"{budget.beyond} {format_bytes(budget.bytes)}; use a smaller {names.chunk} (or leave it out to have one "
            f"chosen), {budget.remedy}")
    tried = grid.chunk
    for chunk in _SMALLER_CHUNKS:
        if chunk >= grid.chunk or chunk < min_chunk(params):
            continue
        tried = chunk
        _, memory = dsm_levels(views, dataclasses.replace(grid, chunk=chunk), h_range, levels,
                               params.model_copy(update={"chunk": chunk}))
        if budget.need(memory) <= budget.bytes:
            plan.notes.append(f"chunks of {chunk} chosen to fit {budget.whose} {format_bytes(budget.bytes)} "
                              f"(chunks of {grid.chunk} would need ~{format_bytes(need)})")
            return chunk
    raise InvalidOptionError(
        f"{names.chunk}: even the smallest chunk tried ({tried}) needs more than "
        f"{budget.whose} {format_bytes(budget.bytes)} (estimated; the height range's candidates set it): narrow "
        f"{names.height_range}, or use {budget.remedy}")
