"""Plan a run before anything runs: check it, size it, refuse it in seconds.

A :class:`Plan` is made before any cluster starts or any chunk is computed,
by :func:`plan_recipe` (``tiledsm dsm`` and ``tiledsm run``),
:func:`plan_sr` (``tiledsm sr``) and :func:`plan_compare`
(``tiledsm compare``). It

- resolves every path to an absolute one (a relative ``--out`` then means
  the same folder to workers started elsewhere, e.g. on an external
  ``--scheduler`` cluster);
- opens every input once (images and their cameras, reference, ``--like``,
  masks, weights, geoid) and refuses a missing or unreadable one naming the
  option and the file;
- checks that the grid (``--bounds``, ``--like`` or the default one), the
  reference and the masks overlap what the images see;
- derives the grid shape and resolution, the chunk count, the pyramid
  levels, the number of dask tasks (the lazy graph is built -- cheap -- and
  counted, never computed) and an estimate of the peak memory of a worker
  (:func:`estimate_worker_memory`);
- says what an earlier run left in ``--out`` that would be reused, and
  refuses (as the run itself would) a store computed from other inputs or
  parameters (:func:`tiledsm.provenance.check_resume`) or a folder another
  live run holds;
- refuses what cannot work with one line naming the option: a grid beyond
  :class:`Limits` (lifted by ``--allow-large``), ``--workers`` < 1, an SR
  scale with no weights, a reference, mask or grid that misses the scene;
- collects warnings that matter (a grid mostly outside the images, a
  reference covering little of the grid, a mask that excludes nothing);
  runs add their own (low completeness) and write them all into
  ``metrics.json`` (``warnings``).

``--dry-run`` prints :meth:`Plan.summary` and exits; a run reuses the plan's
opened views, tie points and lazy DSM, so nothing is done twice.

Conventions: sizes in cells are ``rows x columns``; memory in bytes (MiB
and GiB in text are 2**20 and 2**30 bytes); heights are ellipsoidal metres.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from tiledsm.errors import (
    GridError,
    InputFileError,
    InvalidOptionError,
    MatchingError,
    NoOverlapError,
    OutputLockedError,
    RunTooLargeError,
    TiledsmError,
)

log = logging.getLogger("tiledsm")

__all__ = [
    "CLI_NAMES",
    "RECIPE_NAMES",
    "FieldNames",
    "Limits",
    "InputInfo",
    "LevelPlan",
    "MemoryEstimate",
    "PreparedDSM",
    "Plan",
    "estimate_worker_memory",
    "dsm_levels",
    "check_workers",
    "new_plan",
    "existing_file",
    "seen_fraction",
    "dsm_reuse",
    "check_sr_weights",
    "plan_dsm",
    "plan_recipe",
    "plan_sr",
    "plan_compare",
    "WORKER_BASELINE_MIB",
    "LOW_COMPLETENESS",
    "MOSTLY_OUTSIDE",
]

#: memory of a local dask worker process before its first large task, MiB:
#: measured on the 2-core development machine, an idle worker holds 216 MiB
#: and one that has run a small matching task (numba kernels loaded) 296 MiB,
#: of which ~28 MiB was that task's cost volumes
WORKER_BASELINE_MIB = 270
#: below this completeness inside the common footprint a DSM run warns
LOW_COMPLETENESS = 0.7
#: below this fraction of grid cells seen by every view the plan warns
MOSTLY_OUTSIDE = 0.5
#: samples per grid side when measuring what the images see
_FOOTPRINT_SAMPLES = 200
_MIB = 2**20
_GIB = 2**30


# --------------------------------------------------------------------------- names and limits
@dataclass(frozen=True)
class FieldNames:
    """How the user spelled each input, so that messages name it: command
    line options (:data:`CLI_NAMES`) or recipe field paths
    (:data:`RECIPE_NAMES`)."""

    images: str = "IMAGES"
    rpcs: str = "input.rpcs"
    reference: str = "--reference"
    like: str = "--like"
    bounds: str = "--bounds"
    resolution: str = "--resolution"
    crs: str = "--crs"
    chunk: str = "--chunk"
    levels: str = "--levels"
    height_range: str = "--height-range"
    geoid: str = "--geoid"
    workers: str = "--workers"


#: names of ``tiledsm dsm``'s options
CLI_NAMES = FieldNames()
#: names of a recipe's fields (``tiledsm run``)
RECIPE_NAMES = FieldNames(
    images="input.images", reference="input.reference", like="grid.like", bounds="grid.bounds",
    resolution="grid.resolution", crs="grid.crs", chunk="grid.chunk", levels="match.levels",
    height_range="match.height_range", geoid="output.geoid", workers="cluster.workers",
)


@dataclass(frozen=True)
class Limits:
    """Size limits a run must stay within unless ``allow_large``.

    Attributes
    ----------
    max_cells : int
        Cells of the output grid. 4e9 cells (a 63 000² grid) are 32 GB of
        float32 height and confidence.
    max_chunks : int
        Chunks of the output grid. The client builds and holds the task
        graph, about 30 tasks per chunk at two levels: measured on the
        2-core development machine, 16 384 chunks (a 16384² grid in chunks
        of 128) gave 0.44 M tasks, built in 13 s with 150 MiB more in the
        client, before anything is submitted; the 1.1 M chunks of issue 18's
        ``--resolution 0.001`` would take hours.
    allow_large : bool
        Lift both limits (``--allow-large``).
    """

    max_cells: int = 4 * 10**9
    max_chunks: int = 20_000
    allow_large: bool = False

    def check(self, cells: int, chunks: int, what: str, hint: str) -> None:
        """Raise :class:`~tiledsm.errors.RunTooLargeError` when ``cells`` or
        ``chunks`` exceed the limits (and they are not lifted); ``what``
        starts the message, ``hint`` says how to make the run smaller."""
        if self.allow_large or (cells <= self.max_cells and chunks <= self.max_chunks):
            return
        raise RunTooLargeError(
            f"{what}: {cells:.3g} cells in {chunks:,} chunks, beyond the limits of {self.max_cells:.3g} cells "
            f"and {self.max_chunks:,} chunks; {hint}, or pass --allow-large"
        )


# --------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class InputInfo:
    """One input file of a run: its role (option or field), absolute path
    and what was read from it."""

    role: str
    path: str
    detail: str = ""


@dataclass(frozen=True)
class LevelPlan:
    """One pyramid level of a DSM run.

    Attributes
    ----------
    level : int
        0 = full resolution.
    shape : (int, int)
        Grid cells, rows x columns.
    resolution : float
        Cell size, metres.
    chunks : int
        Number of matching tasks (the level's chunks; a last chunk smaller
        than the halo is merged into its neighbour).
    step : float
        Height step, metres.
    candidates : int
        Most candidate heights a cell searches.
    task_cells : (int, int)
        Cells of the largest matching task (chunk plus halo), rows x columns.
    window_px : int
        Pixels read from one image for the largest task (full resolution,
        before decimation), the largest over the views.
    """

    level: int
    shape: tuple[int, int]
    resolution: float
    chunks: int
    step: float
    candidates: int
    task_cells: tuple[int, int]
    window_px: int


@dataclass(frozen=True)
class MemoryEstimate:
    """Estimated peak memory of one worker (bytes), see
    :func:`estimate_worker_memory`.

    Attributes
    ----------
    total : int
        ``baseline + max(matching, reading)``.
    baseline : int
        The worker process before the task (:data:`WORKER_BASELINE_MIB`).
    cost_volumes : int
        The three cost-volume-sized buffers of a matching task.
    matching : int
        Cost volumes, per-view sample buffers and the decimated image
        windows held while matching.
    reading : int
        Reading the largest image window (the other windows held).
    """

    total: int
    baseline: int
    cost_volumes: int
    matching: int
    reading: int

    def text(self) -> str:
        """One line: total (GiB and MiB) and parts (GiB)."""
        return (
            f"~{self.total / _GIB:.2f} GiB ({self.total / _MIB:.0f} MiB) per worker (baseline {self.baseline / _GIB:.2f} + "
            f"max(matching {self.matching / _GIB:.2f} [cost volumes {self.cost_volumes / _GIB:.2f}], "
            f"reading {self.reading / _GIB:.2f}))"
        )


@dataclass(frozen=True)
class PreparedDSM:
    """What a DSM plan opened and built, handed to the run so nothing is
    done twice: the views (cameras corrected), grid, height range, lazy
    dataset (:func:`tiledsm.dsm.dsm_from_views`) and its report."""

    images: list[str]
    rpcs: list[str | None] | None
    reference: str | None
    views: list
    grid: Any
    h_range: tuple[float, float]
    ds: Any
    report: dict


@dataclass
class Plan:
    """What a run will read, compute, write and reuse, made before it starts.

    Attributes
    ----------
    command : str
        The ``tiledsm`` command (``dsm``, ``run``, ``sr``, ``compare``).
    out : pathlib.Path
        Absolute output folder (or file, for ``sr``).
    cluster : str
        Where the run would compute.
    inputs : list of InputInfo
    grid : str
        The output grid in words (CRS, resolution, shape, chunks).
    height_range : (float, float) or None
    levels : list of LevelPlan
    tasks : int or None
        Tasks of the lazy dask graph (None when not built).
    memory : MemoryEstimate or None
    reuse : str
        What an earlier run in ``out`` leaves that would be reused.
    withdraw : bool
        Products in ``out`` will change: their ``metrics.json``,
        ``recipe.resolved.yaml`` and exports are removed before the run
        starts, so they never describe products of another run.
    warnings, notes : list of str
    limits : Limits
    prepared : PreparedDSM or None
        The DSM stage's prepared inputs (``dsm`` pipeline only).
    product : object or None
        The lazy product the run computes, when the plan built it (``sr``).
    """

    command: str
    out: Path
    cluster: str = ""
    inputs: list[InputInfo] = field(default_factory=list)
    grid: str = ""
    height_range: tuple[float, float] | None = None
    levels: list[LevelPlan] = field(default_factory=list)
    tasks: int | None = None
    memory: MemoryEstimate | None = None
    reuse: str = "nothing (no earlier run in the output folder)"
    withdraw: bool = True
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    limits: Limits = field(default_factory=Limits)
    prepared: PreparedDSM | None = field(default=None, repr=False)
    product: Any = field(default=None, repr=False)

    def warn(self, message: str) -> None:
        """Add a warning (the command prints it; a run logs it in ``run.log``
        and writes it into ``metrics.json``)."""
        self.warnings.append(message)

    def summary(self) -> str:
        """The plan as text (what ``--dry-run`` prints)."""
        rows: list[tuple[str, str]] = [("out", str(self.out)), ("cluster", self.cluster)]
        rows += [("inputs" if k == 0 else "", f"{i.role}: {i.path}" + (f" ({i.detail})" if i.detail else ""))
                 for k, i in enumerate(self.inputs)]
        if self.height_range is not None:
            rows.append(("heights", f"{self.height_range[0]:.1f} .. {self.height_range[1]:.1f} m (ellipsoidal)"))
        if self.grid:
            rows.append(("grid", self.grid))
        for k, lv in enumerate(self.levels):
            rows.append((
                "levels" if k == 0 else "",
                f"L{lv.level}: {lv.shape[0]} x {lv.shape[1]} cells of {lv.resolution:g} m, {lv.chunks} matching tasks, "
                f"step {lv.step:.3f} m, <= {lv.candidates} candidates/cell, largest task "
                f"{lv.task_cells[0]} x {lv.task_cells[1]} cells, image window {lv.window_px / 1e6:.2f} Mpx",
            ))
        if self.tasks is not None:
            rows.append(("tasks", f"{self.tasks:,} in the dask graph"))
        if self.memory is not None:
            rows.append(("memory", self.memory.text()))
        rows.append(("reuse", self.reuse))
        rows += [("notes" if k == 0 else "", n) for k, n in enumerate(self.notes)]
        rows += [("warnings" if k == 0 else "", w) for k, w in enumerate(self.warnings)] or [("warnings", "none")]
        width = max(len(k) for k, _ in rows)
        head = f"plan of tiledsm {self.command} (nothing computed, nothing written)"
        return "\n".join([head] + [f"  {k:<{width}}  {v}" for k, v in rows])


# --------------------------------------------------------------------------- memory
def estimate_worker_memory(
    task_cells: tuple[int, int],
    candidates: int,
    views: int = 2,
    window_px: int = 0,
    decimation: int = 1,
    itemsize: int = 2,
    baseline: int = WORKER_BASELINE_MIB * _MIB,
    search_band: bool = False,
) -> MemoryEstimate:
    """Peak memory of a worker running one matching task.

    A task matches ``ny x nx`` cells (chunk plus halo) with ``nd``
    candidate heights each (:func:`tiledsm.match.sgvll.match_block`). Three
    buffers of ``ny * nx * nd`` float32 live at once: the cost volume
    ``vol`` of ``match_block``, its NaN-filled copy made by
    :func:`tiledsm.match.sgm.aggregate` and the aggregated cost ``S``
    (``winner_take_all`` reads ``S`` and ``vol`` in place). Besides them the
    task holds one float32 sample buffer per view (``nv * ny * nx``), each
    view's image window, decimated by ``f``, and below the coarsest level
    its search band (``h_ref, lo, hi``: ``b = 1``, else ``b = 0``). Reading
    a window of ``W`` pixels (``itemsize`` bytes each, before the volumes
    exist) briefly holds the raw masked array, its float32 masked copy and
    the NaN-filled result::

        matching = 12 ny nx nd + 4 nv ny nx + 12 b ny nx + 4 nv W / f²
        reading  = W (itemsize + 10) + 4 nv W / f²
        peak     = baseline + max(matching, reading)

    Everything else a task allocates (the band's float64 temporaries, freed
    before the volumes exist; the projection lattice, 2-D ZNCC sums, SGM
    line buffers, the returned chunk) is a few 2-D arrays, left out. Tasks
    run one at a time per worker (one thread each).

    Parameters
    ----------
    task_cells : (int, int)
        ``(ny, nx)`` cells of the task (chunk plus halo).
    candidates : int
        ``nd``, the most candidate heights of a cell.
    views : int
        ``nv``.
    window_px : int
        ``W``, full-resolution pixels of the largest image window.
    decimation : int
        ``f`` (``2**level``).
    itemsize : int
        Bytes per pixel of the images on disk.
    baseline : int
        Bytes of the worker before the task (default
        :data:`WORKER_BASELINE_MIB`).
    search_band : bool
        The task searches a band from a coarser level (``b`` above).

    Returns
    -------
    MemoryEstimate
    """
    ny, nx = (int(v) for v in task_cells)
    cells = ny * nx
    held = 4 * views * window_px // (decimation * decimation)
    volumes = 3 * 4 * cells * int(candidates)
    matching = volumes + 4 * views * cells + (12 * cells if search_band else 0) + held
    reading = window_px * (int(itemsize) + 10) + held
    return MemoryEstimate(int(baseline) + max(matching, reading), int(baseline), volumes, matching, reading)


def _largest_task(n: int, chunks: Sequence[int], halo: int) -> int:
    """Longest chunk-plus-halo extent along an axis of ``n`` cells (the
    halo is clipped at the axis ends, as the matching tasks clip it)."""
    start, best = 0, 0
    for c in chunks:
        best = max(best, min(n, start + c + halo) - max(0, start - halo))
        start += c
    return best


def dsm_levels(views, grid, h_range: tuple[float, float], levels: int, params) -> tuple[list[LevelPlan], MemoryEstimate]:
    """Sizes of every pyramid level of a DSM run and the worker memory of
    its largest task.

    Candidates per cell (see :func:`tiledsm.match.sgvll.match_block`): at
    the coarsest level the whole height range, ``ceil((hmax - hmin) / step)
    + 1``; at a finer level the band around the coarser DSM, at most
    ``2 ceil(hole_factor * refine_steps) + 1`` (its width under a coarse
    hole). The image window is that of a task at the grid centre over the
    whole height range (an upper bound for finer levels).

    Returns
    -------
    (list of LevelPlan, MemoryEstimate)
        Levels from coarsest to finest, and the largest estimate over them.
    """
    import numpy as np
    import rasterio

    from tiledsm.dsm import level_geometry, level_layout
    from tiledsm.geometry.footprint import image_window

    halo = params.halo()
    itemsize = 1
    for v in views:
        with rasterio.open(v.path) as src:
            itemsize = max(itemsize, np.dtype(src.dtypes[0]).itemsize)
    span = float(h_range[1] - h_range[0])
    fine_band = 2 * math.ceil(params.search.hole_factor * params.refine_steps - 1e-9) + 1
    out: list[LevelPlan] = []
    worst: MemoryEstimate | None = None
    for level in range(levels - 1, -1, -1):
        geom = level_geometry(views, grid, level, h_range, params)
        g = geom.grid
        chunks = level_layout(g.shape, grid.chunk, params)
        task = tuple(_largest_task(n, ch, halo) for n, ch in zip(g.shape, chunks))
        full = math.ceil(span / geom.step - 1e-9) + 1
        nd = full if level == levels - 1 else min(full, fine_band)
        r0, c0 = (g.height - task[0]) // 2, (g.width - task[1]) // 2
        sub = g.subgrid(r0, r0 + task[0], c0, c0 + task[1])
        window = 0
        for v in views:
            win = image_window(v.rpc, sub, tuple(h_range), v.shape, margin=4 * geom.factor + 8)
            if win is not None:
                window = max(window, (win[1] - win[0]) * (win[3] - win[2]))
        est = estimate_worker_memory(task, nd, len(views), window, geom.factor, itemsize,
                                     search_band=level != levels - 1)
        out.append(LevelPlan(level, g.shape, g.resolution, len(chunks[0]) * len(chunks[1]), geom.step, nd, task, window))
        if worst is None or est.total > worst.total:
            worst = est
    return out, worst


# --------------------------------------------------------------------------- generic checks
def existing_file(path: str | os.PathLike, name: str) -> str:
    """``path`` made absolute; :class:`~tiledsm.errors.InputFileError`
    naming the option/field ``name`` when it is not a file (zarr stores,
    which are folders, are accepted)."""
    p = Path(path).expanduser().resolve()
    if not p.exists():
        raise InputFileError(f"{p}: {name}: no such file")
    if p.is_dir() and p.suffix != ".zarr":
        raise InputFileError(f"{p}: {name}: is a folder, expected a file")
    return str(p)


def check_workers(workers: int | None, name: str = "--workers") -> None:
    """Refuse a worker count below 1 (a cluster without workers waits forever)."""
    if workers is not None and int(workers) < 1:
        raise InvalidOptionError(f"{name}: must be at least 1 worker, got {workers}")


def describe_cluster(config) -> str:
    """Where a :class:`~tiledsm.cluster.ClusterConfig` computes, in words
    (nothing is started or contacted)."""
    if config is None or config.scheduler is None:
        import psutil

        n = (config.workers if config is not None else None) or os.cpu_count() or 1
        limit = psutil.virtual_memory().total / n
        return f"local cluster: {n} single-threaded worker processes, memory limit ~{limit / _GIB:.1f} GiB each"
    if config.scheduler == "synchronous":
        return "in this process (synchronous scheduler)"
    return f"existing cluster at {config.scheduler} (not contacted by the plan)"


def _memory_warning(plan: Plan, config) -> None:
    """Warn when the estimated peak exceeds a local worker's memory limit."""
    if plan.memory is None or (config is not None and config.scheduler is not None):
        return
    import psutil

    n = (config.workers if config is not None else None) or os.cpu_count() or 1
    limit = psutil.virtual_memory().total / n
    if plan.memory.total > limit:
        plan.warn(
            f"estimated peak per worker {plan.memory.total / _GIB:.1f} GiB exceeds the memory limit "
            f"{limit / _GIB:.1f} GiB of each of {n} local workers: use a smaller chunk or fewer workers"
        )


def new_plan(command: str, out: str | os.PathLike, cluster=None, *, limits: Limits = Limits(),
             workers: str = "--workers", folder: bool = True) -> Plan:
    """An empty :class:`Plan` of ``command`` writing ``out`` (made
    absolute), after the checks every command shares: ``workers`` (the
    option or field naming the worker count) >= 1, and, for an output
    ``folder``, no live run holding it (:meth:`tiledsm.provenance.OutputLock.check`)."""
    out = Path(out).expanduser().resolve()
    check_workers(getattr(cluster, "workers", None), workers)
    if folder and out.is_dir():
        from tiledsm.provenance import OutputLock

        OutputLock(out).check()
    return Plan(command, out, cluster=describe_cluster(cluster), limits=limits)


def _raster_header(path: str, name: str) -> dict:
    """CRS, bounds, shape and dtype of a raster; errors name ``name``."""
    import rasterio

    try:
        with rasterio.open(path) as src:
            return {"crs": src.crs, "bounds": tuple(src.bounds), "shape": (src.height, src.width),
                    "dtype": src.dtypes[0], "res": abs(src.transform.a)}
    except rasterio.errors.RasterioIOError as exc:
        raise InputFileError(f"{path}: {name}: not a readable raster ({exc})") from exc


def _overlap_fraction(bounds: Sequence[float], crs, grid) -> float:
    """Fraction of ``grid``'s area inside ``bounds`` (given in ``crs``)."""
    from rasterio.warp import transform_bounds

    left, bottom, right, top = transform_bounds(crs, grid.crs, *bounds, densify_pts=21)
    g = grid.bounds
    w = max(0.0, min(right, g[2]) - max(left, g[0]))
    h = max(0.0, min(top, g[3]) - max(bottom, g[1]))
    return w * h / ((g[2] - g[0]) * (g[3] - g[1]))


def _fmt_bounds(b: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in b) + ")"


def seen_fraction(grid, views, height: float) -> float:
    """Fraction of ``grid``'s cells (sampled on at most ~200² of them)
    whose centre at ``height`` projects inside every view."""
    from tiledsm.dsm import footprint_mask

    step = max(1, math.ceil(max(grid.shape) / _FOOTPRINT_SAMPLES))
    return float(footprint_mask(grid, views, height, step).mean())


# --------------------------------------------------------------------------- DSM
def _dsm_params(recipe, names: FieldNames):
    from tiledsm.recipes import dsm_params

    try:
        return dsm_params(recipe.grid, recipe.match)
    except (ValueError, TypeError) as exc:
        text = str(exc)
        name = names.chunk if "chunk" in text else names.levels if "levels" in text else "match.params"
        raise InvalidOptionError(f"{name}: {text}") from exc


def _explicit_grid(spec, names: FieldNames, like: str | None):
    """The grid a recipe's ``grid`` section names (``like`` or ``bounds``)
    and the option to blame for it, or ``(None, resolution option)``."""
    from tiledsm.geometry.grid import GroundGrid

    if like:
        return GroundGrid.like(like, chunk=spec.chunk), f"{names.like} {like}"
    if spec.bounds:
        return GroundGrid.from_bounds(spec.crs, spec.bounds, spec.resolution, chunk=spec.chunk), names.bounds
    return None, names.resolution


def _grid_text(grid) -> str:
    nby, nbx = grid.numblocks
    return (f"{grid.crs}, {grid.resolution:g} m cells, {grid.height} x {grid.width} cells "
            f"({grid.height * grid.width / 1e6:.3g} Mcells), chunks of {grid.chunk}: {nby} x {nbx} = {nby * nbx}, "
            f"bounds {_fmt_bounds(grid.bounds)}")


def _check_grid_size(grid, limits: Limits, what: str, names: FieldNames) -> None:
    nby, nbx = grid.numblocks
    limits.check(
        grid.width * grid.height, nby * nbx,
        f"{what}: the DSM grid would be {grid.height:,} x {grid.width:,} cells of {grid.resolution:g} m",
        f"choose a coarser {names.resolution}, a smaller grid ({names.bounds}) or a larger {names.chunk}",
    )


def _store_fingerprint(path: Path) -> dict | None:
    import zarr

    try:
        raw = zarr.open_group(str(path), mode="r").attrs.get("fingerprint")
    except Exception as exc:  # noqa: BLE001 - any unreadable store is in the way
        raise TiledsmError(f"{path}: an unreadable store is in the way ({exc}); rerun with --overwrite") from exc
    return json.loads(raw) if isinstance(raw, str) else raw


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
    from tiledsm.provenance import check_resume

    final = out / "dsm.zarr"
    store = ChunkStore(str(final), ("height", "confidence"), grid.shape, (grid.chunk, grid.chunk))
    total = grid.numblocks[0] * grid.numblocks[1]
    for path, state in ((final, "finished"), (store.partial_path, "partial")):
        if not path.exists():
            continue
        if overwrite:
            return f"nothing: --overwrite discards the {state} DSM {path} and computes all {total} chunks", True
        check_resume(_store_fingerprint(path) or {}, fingerprint, str(final))
        if state == "finished":
            return f"all {total} chunks of the finished DSM {final} (same inputs and parameters)", False
        done = int(store.done().sum())
        return f"{done} of {total} chunks of the partial DSM {path}; {total - done} to compute", True
    return f"nothing (no DSM in {out} yet): {total} chunks to compute", True


def plan_dsm(plan: Plan, recipe, cluster=None, *, overwrite: bool = False, names: FieldNames = RECIPE_NAMES) -> Plan:
    """Fill ``plan`` (made by :func:`plan_recipe`) for a ``pipeline: dsm``
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
    from tiledsm.dsm import dsm_from_views, heights_above_geoid, open_views

    out, limits = plan.out, plan.limits
    inp, spec = recipe.input, recipe.grid
    if inp.synth is not None:
        plan.notes.append(f"synthetic scene {inp.synth.size}² px at {inp.synth.gsd} m is made by the run in "
                          f"{out / 'scene'}; its grid, graph and memory are planned then")
        plan.reuse = "decided once the scene is made: a DSM store in the folder is resumed if its fingerprint matches"
        return plan
    images = [existing_file(p, names.images) for p in inp.images]
    rpcs = [None if r is None else existing_file(r, names.rpcs) for r in inp.rpcs] if inp.rpcs else None
    reference = existing_file(inp.reference, names.reference) if inp.reference else None
    like = existing_file(spec.like, names.like) if spec.like else None
    geoid = existing_file(recipe.output.geoid, names.geoid) if recipe.output.geoid else None
    views = open_views(images, rpcs)
    for v in views:
        source = (v.rpc.source or "?").replace(v.path, "").strip(" ()") or v.rpc.source
        plan.inputs.append(InputInfo(names.images, v.path, f"{v.shape[0]} x {v.shape[1]} px, camera: {source}"))
    params = _dsm_params(recipe, names)
    if params.height_range is not None and not params.height_range[0] < params.height_range[1]:
        raise InvalidOptionError(f"{names.height_range}: HMIN must be below HMAX, got {list(params.height_range)}")
    grid, what = _explicit_grid(spec, names, like)
    if like:
        plan.inputs.append(InputInfo(names.like, like, f"its grid: {grid.height} x {grid.width} cells, {grid.crs}"))
    if grid is not None:
        _check_grid_size(grid, limits, what, names)
    from tiledsm.dsm import prepare_views

    h_range, views, report = prepare_views(views, params)
    plan.height_range = h_range
    if "tiepoint_height_range_m" in report:
        _check_given_range(plan, h_range, report["tiepoint_height_range_m"], names.height_range)
    if grid is None:
        from tiledsm.dsm import default_grid

        grid = default_grid(views, h_range, params)
        what = f"{names.resolution} {grid.resolution:g}" if spec.resolution else "the default grid"
        _check_grid_size(grid, limits, what, names)
    report["grid"] = {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height,
                      "chunk": grid.chunk}
    plan.grid = _grid_text(grid)
    _check_seen(plan, grid, views, h_range, what)
    if reference:
        _check_reference(plan, reference, grid, names.reference)
    if geoid:
        plan.inputs.append(InputInfo(names.geoid, geoid))
    ds = dsm_from_views(views, grid, h_range, params)
    if geoid:
        ds = heights_above_geoid(ds, geoid)
        report["vertical_datum"] = ds.attrs["vertical_datum"]
    plan.tasks = len(ds.__dask_graph__())
    plan.levels, plan.memory = dsm_levels(views, grid, h_range, int(ds.attrs["levels"]), params)
    _memory_warning(plan, cluster)
    plan.reuse, plan.withdraw = dsm_reuse(out, grid, json.loads(ds.attrs["fingerprint"]), overwrite)
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


def _check_seen(plan: Plan, grid, views, h_range, what: str) -> None:
    """Refuse a grid no view sees; warn when most of it is unseen."""
    frac = seen_fraction(grid, views, float(sum(h_range) / 2))
    plan.notes.append(f"{frac:.0%} of the grid's cells are seen by every view")
    _refuse_or_warn(
        plan, frac,
        GridError(f"{what}: the DSM grid {_fmt_bounds(grid.bounds)} ({grid.crs}) lies outside what the images see "
                  f"(no sampled cell projects into every view); the DSM would be empty"),
        f"{what}: the grid is mostly outside the images: only {frac:.0%} of its cells are seen by every view",
    )


def _refuse_or_warn(plan: Plan, fraction: float, error: TiledsmError, warning: str) -> None:
    """Raise ``error`` when ``fraction`` (of a grid covered) is 0; add
    ``warning`` to the plan when it is below :data:`MOSTLY_OUTSIDE`."""
    if fraction == 0:
        raise error
    if fraction < MOSTLY_OUTSIDE:
        plan.warn(warning)


def _check_reference(plan: Plan, path: str, grid, name: str) -> None:
    """Refuse a reference raster without CRS or outside the grid; warn when
    it covers little of it."""
    head = _raster_header(path, name)
    if head["crs"] is None:
        raise GridError(f"{path}: {name}: has no CRS, so it cannot be compared with the DSM grid")
    frac = _overlap_fraction(head["bounds"], head["crs"], grid)
    plan.inputs.append(InputInfo(name, path, f"{head['shape'][0]} x {head['shape'][1]} cells, {head['crs']}, "
                                             f"covers {frac:.0%} of the grid"))
    _refuse_or_warn(
        plan, frac,
        NoOverlapError(f"{path}: {name}: covers none of the DSM grid (reference bounds {_fmt_bounds(head['bounds'])} "
                       f"in {head['crs']}, grid bounds {_fmt_bounds(grid.bounds)} in {grid.crs})"),
        f"{path}: {name}: covers only {frac:.0%} of the DSM grid",
    )


# --------------------------------------------------------------------------- recipes
def plan_recipe(
    recipe,
    out: str | os.PathLike,
    cluster=None,
    *,
    overwrite: bool = False,
    limits: Limits = Limits(),
    names: FieldNames = RECIPE_NAMES,
    command: str = "run",
) -> Plan:
    """Plan any recipe into the folder ``out`` (made absolute): the workers
    and the folder's lock first, then a full plan for ``pipeline: dsm``
    (:func:`plan_dsm`); for the workflows (``sr_dsm``, ``deformation``,
    ``train_sr``) the checks that need no stage to run -- inputs exist,
    SR weights exist for ``sr.scale``, a stable mask overlaps the scene --
    while their stages plan their own grids when they run."""
    plan = new_plan(command, out, cluster, limits=limits, workers=names.workers)
    if recipe.pipeline == "dsm":
        return plan_dsm(plan, recipe, cluster, overwrite=overwrite, names=names)
    plan.notes.append(f"pipeline {recipe.pipeline}: each stage plans its grid, graph and memory when it runs")
    plan.reuse = "stores of an earlier run with the same fingerprint (checked by each stage)"
    for role, path in _recipe_files(recipe.model_dump(), ""):
        plan.inputs.append(InputInfo(role, existing_file(path, role)))
    sr = getattr(recipe, "sr", None)
    if sr is not None:
        check_sr_weights(sr.models, sr.scale, "sr.scale:",
                         "use an sr.scale with weights, or leave those models out of sr.models")
    mask = getattr(getattr(recipe, "compare", None), "stable_mask", None)
    pre = getattr(recipe.input, "pre", None)
    if mask and pre is not None:
        _check_mask_sees_views(existing_file(mask, "compare.stable_mask"), pre.images, pre.rpcs, "compare.stable_mask")
    return plan


#: recipe fields that hold input file paths (outputs such as ``train.out`` are not)
_INPUT_KEYS = {"images", "rpcs", "reference", "like", "geoid", "stable_mask", "dem", "truth_dh", "truth_mask"}


def _recipe_files(data: Any, where: str) -> list[tuple[str, str]]:
    """``(field path, file)`` of every input file a recipe names."""
    if isinstance(data, dict):
        return [x for k, v in data.items() for x in _recipe_files(v, f"{where}.{k}" if where else k)]
    if isinstance(data, list):
        return [x for v in data for x in _recipe_files(v, where)]
    key = where.rsplit(".", 1)[-1]
    return [(where, data)] if key in _INPUT_KEYS and isinstance(data, str) else []


def check_sr_weights(models: Sequence[str], scale: int, scale_name: str, remedy: str) -> None:
    """Refuse an SR scale for which a requested network has no shipped
    weights; the message names ``scale_name`` and ends with ``remedy``
    (what to do instead, in the caller's options)."""
    from tiledsm.sr.registry import WEIGHTLESS, available_weights, weights_path

    missing = [m for m in models if m in _sr_networks() and m not in WEIGHTLESS and not weights_path(m, scale).exists()]
    if missing:
        have = ", ".join(f"{n} x{s}" for n, s in available_weights()) or "none"
        raise InvalidOptionError(
            f"{scale_name} {scale}: no shipped weights for {', '.join(missing)} at x{scale} (shipped: {have}); {remedy}"
        )


def _sr_networks() -> list[str]:
    from tiledsm.sr.registry import MODELS

    return MODELS.names()


def _check_mask_sees_views(mask: str, images: Sequence[str], rpcs, name: str) -> None:
    """Refuse exclusion polygons that lie outside what the views see."""
    import numpy as np

    from tiledsm.compare.stable import read_polygons
    from tiledsm.dsm import open_views
    from tiledsm.geometry.footprint import ground_polygon

    views = open_views(images, rpcs)
    boxes = []
    for v in views:
        r = v.rpc
        poly = np.concatenate([ground_polygon(r, v.shape, h) for h in (r.height_off - r.height_scale,
                                                                       r.height_off + r.height_scale)])
        boxes.append((poly[:, 0].min(), poly[:, 1].min(), poly[:, 0].max(), poly[:, 1].max()))
    lon0, lat0 = max(b[0] for b in boxes), max(b[1] for b in boxes)
    lon1, lat1 = min(b[2] for b in boxes), min(b[3] for b in boxes)
    if not _polygons_touch(read_polygons(mask, "EPSG:4326"), (lon0, lat0, lon1, lat1)):
        raise NoOverlapError(
            f"{mask}: {name}: no polygon lies in the scene the images see (lon/lat box "
            f"({lon0:.5f}, {lat0:.5f}, {lon1:.5f}, {lat1:.5f})): it would exclude nothing"
        )


def _polygons_touch(geoms: list[dict], box: Sequence[float]) -> bool:
    """Whether any GeoJSON polygon's bounding box meets ``box``
    ``(xmin, ymin, xmax, ymax)`` (same CRS)."""
    import numpy as np

    for g in geoms:
        rings = g["coordinates"] if g["type"] == "Polygon" else [r for p in g["coordinates"] for r in p]
        xy = np.concatenate([np.asarray(r, float)[:, :2] for r in rings])
        if xy[:, 0].min() <= box[2] and xy[:, 0].max() >= box[0] and xy[:, 1].min() <= box[3] and xy[:, 1].max() >= box[1]:
            return True
    return False


# --------------------------------------------------------------------------- sr and compare
def plan_sr(
    image: str,
    output: str,
    *,
    model: str,
    scale: int,
    weights: str | None = None,
    chunk: int = 512,
    cluster=None,
    **sr_options: Any,
) -> Plan:
    """Plan ``tiledsm sr``: the image and its camera open, the output is a
    GeoTIFF or zarr path in an existing folder, ``model`` has weights at
    ``scale`` (or ``weights`` exists), and the lazy tiled graph
    (:func:`tiledsm.sr.infer.super_resolve` with ``sr_options``: device,
    blur_sigma, noise) is built and counted; :attr:`Plan.product` is it.

    Returns
    -------
    Plan
    """
    from tiledsm.io import open_scene
    from tiledsm.sr.infer import super_resolve

    plan = new_plan("sr", output, cluster, folder=False)
    out = plan.out
    if chunk < 16:
        raise InvalidOptionError(f"--chunk: {chunk} is too small (at least 16 pixels)")
    if scale < 2:
        raise InvalidOptionError(f"--scale: must be an integer >= 2, got {scale}")
    if out.suffix.lower() not in (".tif", ".tiff", ".zarr"):
        raise InvalidOptionError(f"{out}: OUTPUT: must end in .tif/.tiff or .zarr")
    if not out.parent.is_dir():
        raise InputFileError(f"{out}: OUTPUT: folder {out.parent} does not exist")
    src = existing_file(image, "INPUT")
    scene = open_scene(src, chunks=chunk)
    bit_depth = sr_options.pop("bit_depth", None)
    if bit_depth is not None:
        scene.attrs["bit_depth"] = bit_depth
    plan.inputs.append(InputInfo("INPUT", src, f"{scene.sizes['y']} x {scene.sizes['x']} px, "
                                               f"camera: {scene.attrs.get('camera_source', '?')}"))
    if weights:
        from tiledsm.sr.registry import load_weights

        weights = existing_file(weights, "--weights")
        plan.inputs.append(InputInfo("--weights", weights))
        net = load_weights(weights, sr_options.get("device", "cpu"))
    else:
        check_sr_weights([model], scale, "--scale", "pass --weights FILE (see `tiledsm train-sr`) or use --model bicubic")
        net = model
    plan.product = super_resolve(scene, net, scale, **sr_options)
    ny, nx = plan.product.sizes["y"], plan.product.sizes["x"]
    nby, nbx = -(-scene.sizes["y"] // chunk), -(-scene.sizes["x"] // chunk)
    plan.grid = f"{ny} x {nx} px output (x{scale}), tiles of {chunk} input px: {nby} x {nbx} = {nby * nbx}"
    plan.tasks = len(plan.product.data.__dask_graph__())
    plan.notes.append("memory per worker is not estimated for SR")
    plan.reuse = f"nothing: {out} is written whole" + (" (replacing the existing file)" if out.exists() else "")
    return plan


def plan_compare(ref: str, other: str, out: str, *, stable_mask: str | None, chunks: int, cluster=None) -> Plan:
    """Plan ``tiledsm compare``: both DSMs open with a CRS and overlap; the
    stable mask reads, lies in the reference's extent and excludes some
    valid cell (sampled; a warning otherwise).

    Returns
    -------
    Plan
    """
    import numpy as np

    plan = new_plan("compare", out, cluster)
    heads = {}
    for name, path in (("REF", ref), ("OTHER", other)):
        p = existing_file(path, name)
        h = _raster_header(p, name)
        if h["crs"] is None:
            raise GridError(f"{p}: {name}: has no CRS; a DSM to compare needs one")
        heads[name] = (p, h)
        plan.inputs.append(InputInfo(name, p, f"{h['shape'][0]} x {h['shape'][1]} cells of {h['res']:g}, {h['crs']}"))
    (ref_p, rh), (oth_p, oh) = heads["REF"], heads["OTHER"]
    from tiledsm.geometry.grid import GroundGrid

    grid = GroundGrid.like(ref_p, chunk=chunks)
    frac = _overlap_fraction(oh["bounds"], oh["crs"], grid)
    _refuse_or_warn(plan, frac, NoOverlapError(f"{oth_p}: OTHER: has no ground in common with REF {ref_p}"),
                    f"{oth_p}: OTHER covers only {frac:.0%} of REF's grid")
    nby, nbx = grid.numblocks
    plan.grid = _grid_text(grid) + f"; OTHER covers {frac:.0%} of it"
    if stable_mask:
        from tiledsm.compare.stable import exclusion_mask, read_polygons

        mask = existing_file(stable_mask, "--stable-mask")
        geoms = read_polygons(mask, rh["crs"])
        step = max(1, math.ceil(max(grid.shape) / 1000))
        import rasterio

        with rasterio.open(ref_p) as src:
            valid = np.isfinite(src.read(1, out_shape=(-(-grid.height // step), -(-grid.width // step)),
                                         masked=True).filled(np.nan).astype(float))
        from affine import Affine

        t = grid.transform @ Affine.scale(grid.width / valid.shape[1], grid.height / valid.shape[0])
        excluded = exclusion_mask(geoms, t, valid.shape) if geoms else np.zeros(valid.shape, bool)
        plan.inputs.append(InputInfo("--stable-mask", mask, f"{len(geoms)} polygons, exclude "
                                                            f"{(excluded & valid).mean():.1%} of REF's cells"))
        if not _polygons_touch(geoms, grid.bounds):
            raise NoOverlapError(f"{mask}: --stable-mask: no polygon lies within REF's extent "
                                 f"{_fmt_bounds(grid.bounds)} ({rh['crs']}): it would exclude nothing")
        if not (excluded & valid).any():
            plan.warn(f"{mask}: --stable-mask excludes no valid cell of REF (sampled every {step} cells)")
    plan.reuse = "nothing: the comparison is recomputed whole (products replaced when all succeeded)"
    return plan
