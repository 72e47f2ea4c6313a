"""The plan itself: field names, limits, :class:`Plan` and the checks every command shares."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from tiledsm.errors import InputFileError, InvalidOptionError, RunTooLargeError, TiledsmError

if TYPE_CHECKING:  # the DSM stage's memory model: only named here
    from tiledsm.dsm.memory import LevelPlan, MemoryEstimate


#: below this completeness inside the common footprint a DSM run warns
LOW_COMPLETENESS = 0.7
#: below this fraction of grid cells seen by every view the plan warns
MOSTLY_OUTSIDE = 0.5
#: samples per grid side when measuring what the images see
_FOOTPRINT_SAMPLES = 200


# --------------------------------------------------------------------------- names and limits
@dataclass(frozen=True)
class FieldNames:
    """How the user spelled each input a plan names, so that messages name
    it: recipe field paths (:data:`RECIPE_NAMES`, the defaults) or a
    command's options (:meth:`of_options`)."""

    images: str = "input.images"
    rpcs: str = "input.rpcs"
    reference: str = "input.reference"
    like: str = "grid.like"
    bounds: str = "grid.bounds"
    resolution: str = "grid.resolution"
    crs: str = "grid.crs"
    chunk: str = "grid.chunk"
    levels: str = "match.levels"
    height_range: str = "match.height_range"
    geoid: str = "output.geoid"
    workers: str = "cluster.workers"
    scheduler: str = "cluster.address"

    @classmethod
    def of_options(cls, options: dict[str, str]) -> "FieldNames":
        """The names a command's options give these fields: ``options`` is
        ``{field path: option}`` of the command's spec
        (:func:`tiledsm.recipes.options_of`); a field takes the option of
        the deepest field holding it (``output.geoid`` that of ``output``),
        or keeps its path when none has one (``input.rpcs``)."""
        def spelled(path: str) -> str:
            holders = [f for f in options if path == f or path.startswith(f + ".")]
            return options[max(holders, key=len)] if holders else path

        return cls(**{f.name: spelled(f.default) for f in fields(cls)})


#: names of a recipe's fields (``tiledsm run``)
RECIPE_NAMES = FieldNames()


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
        Absolute output folder.
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
    recipe : object or None
        The recipe as the run must use it when the plan changed it (a chunk
        side chosen to fit a worker's memory); its resolved form is what
        ``recipe.resolved.yaml`` records.
    stages : list of (str, Plan)
        The plans of the DSMs a pipeline makes (e.g. ``pre`` and ``post``
        of a deformation run), each into its own sub-folder; the summary
        shows each one's grid, levels and memory.
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
    recipe: Any = field(default=None, repr=False)
    stages: list[tuple[str, "Plan"]] = field(default_factory=list, repr=False)

    def warn(self, message: str) -> None:
        """Add a warning (the command prints it; a run logs it in ``run.log``
        and writes it into ``metrics.json``)."""
        self.warnings.append(message)

    def summary(self) -> str:
        """The plan as text (what ``--dry-run`` prints)."""
        rows: list[tuple[str, str]] = [("out", str(self.out)), ("cluster", self.cluster)]
        rows += [("inputs" if k == 0 else "", f"{i.role}: {i.path}" + (f" ({i.detail})" if i.detail else ""))
                 for k, i in enumerate(self.inputs)]
        rows += self._stage_rows()
        for name, stage in self.stages:
            rows.append((name, f"DSM into {stage.out}"))
            rows += [(f"{name} {key}" if key else "", value) for key, value in stage._stage_rows() + [("reuse", stage.reuse)]]
        rows.append(("reuse", self.reuse))
        rows += [("notes" if k == 0 else "", n) for k, n in enumerate(self.notes)]
        rows += [("warnings" if k == 0 else "", w) for k, w in enumerate(self.warnings)] or [("warnings", "none")]
        width = max(len(k) for k, _ in rows)
        head = f"plan of tiledsm {self.command} (nothing computed, nothing written)"
        return "\n".join([head] + [f"  {k:<{width}}  {v}" for k, v in rows])

    def _stage_rows(self) -> list[tuple[str, str]]:
        """Heights, grid, levels, tasks and memory, as summary rows."""
        rows: list[tuple[str, str]] = []
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
        return rows


# --------------------------------------------------------------------------- generic checks
def namer(model, plan: Plan):
    """``name(path)``: how a message of ``plan`` names the field ``path`` of
    the recipe model ``model`` (:func:`tiledsm.recipes.spelling`): its
    option when a stage's own command made the plan (``tiledsm ortho``...),
    its path under ``tiledsm run``."""
    from tiledsm.recipes import spelling

    names = spelling(model, by_option=plan.command != "run")
    return lambda path: names.get(path, path)


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


def readable_raster(path: str, name: str) -> str:
    """``path`` (absolute, as :func:`existing_file` returns it) after reading
    the last row of every band: a truncated or corrupt raster (whose header
    opens but whose pixels do not) is refused now, naming ``name``, rather
    than inside a task. Cheap: one row of blocks."""
    import rasterio
    from rasterio.windows import Window

    try:
        with rasterio.open(path) as src:
            src.read(window=Window(0, src.height - 1, src.width, 1))
    except rasterio.errors.RasterioError as exc:
        raise InputFileError(f"{path}: {name}: cannot read its pixels ({_root_message(exc)})") from None
    return path


def _root_message(exc: BaseException) -> str:
    """The GDAL message behind rasterio's "See previous exception"."""
    while exc.__context__ is not None and "previous exception" in str(exc):
        exc = exc.__context__
    return str(exc)


def check_workers(workers: int | None, name: str = "--workers") -> None:
    """Refuse a worker count below 1 (a cluster without workers waits forever)."""
    if workers is not None and int(workers) < 1:
        raise InvalidOptionError(f"{name}: must be at least 1 worker, got {workers}")


def describe_cluster(config) -> str:
    """Where a :class:`~tiledsm.cluster.ClusterConfig` computes, in words
    (nothing is started or contacted)."""
    if config is not None and getattr(config, "jobqueue", None) is not None:
        jq = config.jobqueue
        n = jq.processes or jq.cores
        return (
            f"{jq.kind} jobs (dask-jobqueue): {jq.minimum_jobs}..{jq.maximum_jobs} jobs of {jq.cores} cores, "
            f"{jq.memory}, {jq.walltime}, {n} single-threaded workers each"
            + (f", queue {jq.queue}" if jq.queue else "") + (f", account {jq.account}" if jq.account else "")
        )
    if config is None or config.scheduler is None:
        from tiledsm.cluster import ClusterConfig, worker_memory_budget

        n = (config or ClusterConfig()).local_workers
        limit = worker_memory_budget(config)
        return f"local cluster: {n} single-threaded worker processes, memory limit ~{limit / 2**30:.1f} GiB each"
    if config.scheduler == "synchronous":
        return "in this process (synchronous scheduler)"
    if config.scheduler == "threads":
        return f"in this process: {config.local_workers} threads (threaded scheduler, no worker processes)"
    return f"existing cluster at {config.scheduler}"


def is_address(config) -> bool:
    """Whether a :class:`~tiledsm.cluster.ClusterConfig` names an existing
    scheduler (rather than a cluster or scheduler this process starts)."""
    return config is not None and config.scheduler not in (None, "threads", "synchronous")


def new_plan(command: str, out: str | os.PathLike, cluster=None, *, limits: Limits = Limits(),
             workers: str = "--workers", folder: bool = True, scheduler: str = "--scheduler") -> Plan:
    """An empty :class:`Plan` of ``command`` writing ``out`` (made
    absolute), after the checks every command shares: ``workers`` (the
    option or field naming the worker count) >= 1; an existing scheduler
    (``scheduler``: the option or field naming its address) answers, in
    seconds (:func:`tiledsm.cluster.check_scheduler`); for an output
    ``folder``, no live run holding it (:meth:`tiledsm.io.lock.OutputLock.check`)."""
    out = Path(out).expanduser().resolve()
    check_workers(getattr(cluster, "workers", None), workers)
    where = describe_cluster(cluster)
    warnings = []
    if is_address(cluster):
        from tiledsm.cluster import check_scheduler

        n = check_scheduler(cluster.scheduler, scheduler)
        where += f": {n} workers now (the plan contacted it)"
        if n == 0:
            warnings.append(f"{scheduler} {cluster.scheduler}: the scheduler has no workers yet; the run waits "
                            "until some join")
    if folder and out.exists() and not out.is_dir():
        raise InvalidOptionError(f"{out}: --out: is a file, expected a folder (new or from an earlier run)")
    if folder and out.is_dir():
        from tiledsm.io.lock import OutputLock

        OutputLock(out).check()
    check_writable(out if folder else out.parent, "--out" if folder else "OUTPUT")
    return Plan(command, out, cluster=where, limits=limits, warnings=warnings)


def check_writable(folder: Path, name: str) -> None:
    """Refuse an output ``folder`` (absolute) that the run could not write:
    it, or the nearest folder above it that exists (where it would be
    created), is on a read-only file system or not writable by this user.
    The message names ``name`` (the option), that folder and the reason."""
    from tiledsm.writable import unwritable

    fault = unwritable(folder)
    if fault is None:
        return
    existing, reason = fault
    where = "" if existing == folder else f" (where {folder} would be created)"
    raise InvalidOptionError(f"{existing}: {name}: cannot write into this folder{where}: {reason}")

def raster_header(path: str, name: str) -> dict:
    """CRS, bounds, shape and dtype of a raster (a GDAL raster, or a
    ``.zarr`` store of tiledsm holding a 2-D variable); errors name
    ``name``."""
    import rasterio

    if Path(path).is_dir():
        a = store_raster(path, name)
        return {"crs": a.rio.crs, "bounds": tuple(a.rio.bounds()), "shape": a.rio.shape,
                "dtype": str(a.dtype), "res": abs(a.rio.resolution()[0])}
    try:
        with rasterio.open(path) as src:
            return {"crs": src.crs, "bounds": tuple(src.bounds), "shape": (src.height, src.width),
                    "dtype": src.dtypes[0], "res": abs(src.transform.a)}
    except rasterio.errors.RasterioIOError as exc:
        raise InputFileError(f"{path}: {name}: not a readable raster ({exc})") from exc


def store_raster(path: str, name: str):
    """The 2-D raster of a tiledsm ``.zarr`` store
    (:func:`tiledsm.io.open_raster_product`), which must have a CRS
    (that error names ``name`` too)."""
    from tiledsm.io import open_raster_product

    a = open_raster_product(path)  # its errors name the path
    if a.rio.crs is None:
        raise InputFileError(f"{path}: {name}: the store's raster has no CRS")
    return a


def overlap_fraction(bounds: Sequence[float], crs, grid) -> float:
    """Fraction of ``grid``'s area inside ``bounds`` (given in ``crs``)."""
    from rasterio.warp import transform_bounds

    left, bottom, right, top = transform_bounds(crs, grid.crs, *bounds, densify_pts=21)
    g = grid.bounds
    w = max(0.0, min(right, g[2]) - max(left, g[0]))
    h = max(0.0, min(top, g[3]) - max(bottom, g[1]))
    return w * h / ((g[2] - g[0]) * (g[3] - g[1]))


def format_bounds(b: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in b) + ")"


def seen_fraction(grid, views, height: float) -> float:
    """Fraction of ``grid``'s cells (sampled on at most ~200² of them)
    whose centre at ``height`` projects inside every view."""
    from tiledsm.dsm import footprint_mask

    step = max(1, math.ceil(max(grid.shape) / _FOOTPRINT_SAMPLES))
    return float(footprint_mask(grid, views, height, step).mean())




def check_earlier_run(recipe, out: Path, overwrite: bool, name: str = "--out") -> None:
    """Refuse to replace, without ``overwrite``, the products of an earlier
    run of other inputs or parameters in the folder ``out``: a stage whose
    products are rewritten whole (``sr``, ``compare``) resumes only its own
    run, whose ``recipe.resolved.yaml`` equals ``recipe``'s resolved form.
    A folder without one (new, or a run killed before it finished) is free.
    The message names ``name`` (the option or field of the folder)."""
    import yaml

    from pydantic import ValidationError

    stored = out / "recipe.resolved.yaml"
    if overwrite or not stored.is_file():
        return
    try:
        # read through the model: a field added since that run (at its
        # default) does not make the same options another run
        earlier = type(recipe).model_validate(yaml.safe_load(stored.read_text()))
        same = earlier.model_dump(mode="json") == recipe.model_dump(mode="json")
    except (OSError, yaml.YAMLError, ValidationError, TypeError):
        same = False
    if not same:
        raise InvalidOptionError(f"{out}: {name}: holds a run of other inputs or options ({stored.name}); pass "
                                 "--overwrite to replace it, or choose another folder")


def stored_fingerprint(path: Path) -> dict:
    """The fingerprint a chunk store holds (``{}`` for none: a store of an
    older tiledsm, which no run resumes)."""
    import json

    import zarr

    try:
        raw = zarr.open_group(str(path), mode="r").attrs.get("fingerprint")
    except Exception as exc:  # noqa: BLE001 - any unreadable store is in the way
        raise TiledsmError(f"{path}: an unreadable store is in the way ({exc}); rerun with --overwrite") from exc
    return (json.loads(raw) if isinstance(raw, str) else raw) or {}


def store_reuse(store, product: str, fingerprint: dict, overwrite: bool) -> tuple[str, bool]:
    """What of a chunk store's finished (``store.path``) or partial
    (``store.partial_path``) form a run would reuse, said in one line, and
    whether the store will change (the run then withdraws its products).

    Parameters
    ----------
    store : tiledsm.io.ChunkStore
        The store the run writes.
    product : str
        What it holds, for the message (``"DSM"``, ``"ortho"``).
    fingerprint : dict
        The run's inputs and parameters.
    overwrite : bool
        ``--overwrite``: nothing is reused.

    Raises
    ------
    FingerprintMismatchError
        The stored product was computed from other inputs or parameters
        and not ``overwrite`` (the message the run itself would give).
    """
    from tiledsm.provenance import check_resume

    final = Path(store.path)
    total = store.numblocks[0] * store.numblocks[1]
    for path, state in ((final, "finished"), (Path(store.partial_path), "partial")):
        if not path.exists():
            continue
        if overwrite:
            return f"nothing: --overwrite discards the {state} {product} {path} and computes all {total} chunks", True
        check_resume(stored_fingerprint(path), fingerprint, str(final))
        if state == "finished":
            return f"all {total} chunks of the finished {product} {final} (same inputs and parameters)", False
        done = int(store.done().sum())
        return f"{done} of {total} chunks of the partial {product} {path}; {total - done} to compute", True
    return f"nothing (no {product} in {final.parent} yet): {total} chunks to compute", True


def refuse_or_warn(plan: Plan, fraction: float, error: TiledsmError, warning: str) -> None:
    """Raise ``error`` when ``fraction`` (of a grid covered) is 0; add
    ``warning`` to the plan when it is below :data:`MOSTLY_OUTSIDE`."""
    if fraction == 0:
        raise error
    if fraction < MOSTLY_OUTSIDE:
        plan.warn(warning)
