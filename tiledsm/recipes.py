"""Recipe parts shared by every pipeline: YAML files that describe a whole
run, validated by a schema.

A recipe names its ``pipeline`` (a key of :data:`tiledsm.pipelines.PIPELINES`,
where each pipeline's own recipe model lives beside its runner), its
inputs, the stage parameters, the ground grid, the cluster and the
outputs. This module holds the parts they share (:class:`StrictModel`,
inputs, grid, matching, cluster, output), reading a recipe file
(:func:`read_recipe`) and writing the resolved one (:func:`dump_resolved`).
Unknown or mistyped fields are errors that name the field path. The
resolved recipe (every default filled in) is written next to the outputs
as ``recipe.resolved.yaml``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, Optional

import yaml
from pydantic import AfterValidator, BaseModel, Field, ValidationError, field_validator, model_validator

from tiledsm.errors import RecipeError
from tiledsm.match.params import SGVLLParams
from tiledsm.spec import StrictModel, option  # the base lives apart: stage parameter models share it

__all__ = [
    "StrictModel", "SynthInput", "InputSpec", "GridSpec", "MatchSpec", "JobQueueSpec", "ClusterSpec", "OutputSpec",
    "ChunkSide", "grid_from_spec", "check_size", "load_cluster", "read_recipe", "format_errors", "dump_resolved",
    "option", "options_of", "spelling", "INPUT_KEYS",
]


def options_of(model: type[BaseModel], prefix: str = "") -> dict[str, str]:
    """``{field path: option}`` of every field of ``model`` (sub-models
    walked, ``Optional`` ones too) whose metadata names an option
    (:func:`option`); a sub-model field's own option covers its model-level
    checks (e.g. ``grid`` -> ``--like/--bounds``)."""
    import typing

    found: dict[str, str] = {}
    for name, info in model.model_fields.items():
        path = f"{prefix}{name}"
        extra = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
        if "option" in extra and extra["option"] is None:
            continue
        if "option" in extra:
            found[path] = extra["option"]
        for arg in (info.annotation, *typing.get_args(info.annotation)):
            if isinstance(arg, type) and issubclass(arg, BaseModel):
                found.update(options_of(arg, path + "."))
    return found


def spelling(model: type[BaseModel], by_option: bool) -> dict[str, str]:
    """How messages name each field of ``model`` that has an option: the
    option when a command built the recipe from its options (``by_option``),
    the field path otherwise (a recipe file, ``tiledsm run``)."""
    return {f: o if by_option else f for f, o in options_of(model).items()}


class SynthInput(StrictModel):
    """A synthetic scene made by :mod:`tiledsm.synth` (known truth)."""

    size: int = Field(512, ge=64, description="image side, pixels")
    gsd: float = Field(0.5, gt=0, description="ground sample distance, metres")
    bh: float = Field(0.4, gt=0.05, le=1.0, description="base-to-height ratio of the first two views")
    seed: int = 0
    views: int = Field(2, ge=2, le=3)
    event: bool = False


class InputSpec(StrictModel):
    """Either a synthetic scene (``synth``) or images with RPCs (``images``,
    cameras in their tags, a sidecar, or ``rpcs``)."""

    synth: Optional[SynthInput] = None
    images: Optional[list[str]] = Field(None, min_length=2, json_schema_extra=option("IMAGES"))
    rpcs: Optional[list[Optional[str]]] = None
    reference: Optional[str] = Field(None, description="reference DSM for metrics (GeoTIFF)",
                                     json_schema_extra=option("--reference"))

    @model_validator(mode="after")
    def _one_source(self):
        if (self.synth is None) == (self.images is None):
            raise ValueError("give exactly one of 'synth' (a synthetic scene) or 'images'")
        if self.rpcs is not None and (self.images is None or len(self.rpcs) != len(self.images)):
            raise ValueError("'rpcs' needs one entry per image")
        return self


def _even_chunk(value: int) -> int:
    # even chunks keep coarse and fine chunk corners aligned
    if value % 2:
        raise ValueError(f"must be even (a coarser level's chunks are half as large), got {value}")
    return value


#: a chunk side of a DSM grid, cells: even and at least 32 (``grid.chunk``, :attr:`tiledsm.dsm.DSMParams.chunk`)
ChunkSide = Annotated[int, Field(ge=32), AfterValidator(_even_chunk)]


class GridSpec(StrictModel):
    """Output ground grid; everything optional (derived from the views)."""

    like: Optional[str] = Field(None, description="align to this raster's grid (CRS, transform, shape)",
                                json_schema_extra=option("--like"))
    crs: Optional[str] = Field(None, json_schema_extra=option("--crs"))
    resolution: Optional[float] = Field(None, gt=0, description="metres", json_schema_extra=option("--resolution"))
    bounds: Optional[tuple[float, float, float, float]] = Field(None, description="xmin ymin xmax ymax, grid CRS",
                                                                json_schema_extra=option("--bounds"))
    chunk: ChunkSide = Field(512, description="chunk side, cells", json_schema_extra=option("--chunk"))

    @model_validator(mode="after")
    def _consistent(self):
        if self.like and (self.crs or self.bounds or self.resolution):
            raise ValueError("give either 'like' or crs/resolution/bounds, not both")
        if self.bounds and not (self.crs and self.resolution):
            raise ValueError("'bounds' needs 'crs' and 'resolution'")
        return self


class MatchSetup(StrictModel):
    """The pyramid levels and the height range the matching searches, and
    the tie points' relative correction: the fields a recipe's ``match``
    section (:class:`MatchSpec`) and the engine's parameters
    (:class:`tiledsm.dsm.DSMParams`) share, declared once here."""

    levels: Optional[int] = Field(None, ge=1, le=6, description="pyramid levels; default: from the height range",
                                  json_schema_extra=option("--levels"))
    height_range: Optional[tuple[float, float]] = Field(
        None, description="scene height range, ellipsoidal metres; default: from tie points",
        json_schema_extra=option("--height-range"))
    height_margin: float = Field(10.0, ge=0, description="metres added on both sides of the tie-point height range")
    relative_correction: bool = Field(True, description="correct the relative pointing error of views 2.. by a "
                                      "translation estimated from tie points")


class MatchSpec(MatchSetup):
    """Dense matching parameters of the DSM stage (with the grid's, the
    engine's :class:`tiledsm.dsm.DSMParams`: :meth:`~tiledsm.dsm.DSMParams.of_recipe`)."""

    # every value shown in the resolved recipe; --device sets params.device (its field's option)
    params: SGVLLParams = Field(SGVLLParams(), description="matching parameters (SGVLLParams)")


def grid_from_spec(grid: GridSpec):
    """The :class:`~tiledsm.geometry.grid.GroundGrid` a recipe's ``grid``
    section names (``like`` or ``bounds``), or ``None`` when the stage
    derives it from the views (then ``crs``/``resolution`` go through
    :meth:`tiledsm.dsm.DSMParams.of_recipe`)."""
    from tiledsm.geometry.grid import GroundGrid
    from tiledsm.io.grids import grid_like

    if grid.like:
        return grid_like(grid.like, chunk=grid.chunk)
    if grid.bounds:
        return GroundGrid.from_bounds(grid.crs, grid.bounds, grid.resolution, chunk=grid.chunk)
    return None


def check_size(value: str, name: str, error: type[Exception] | None = None) -> int:
    """Bytes of a memory size in dask's syntax (``4GiB``, ``500MB``); an
    error naming ``name`` otherwise (:class:`~tiledsm.errors.InvalidOptionError`
    by default)."""
    from dask.utils import parse_bytes

    from tiledsm.errors import InvalidOptionError

    try:
        n = int(parse_bytes(value))
    except (ValueError, TypeError):
        n = 0
    if n <= 0:
        raise (error or InvalidOptionError)(f"{name}: {value!r} is not a memory size (e.g. 4GiB, 500MB)")
    return n


class JobQueueSpec(StrictModel):
    """Resources of one batch job (see :class:`tiledsm.cluster.JobQueueConfig`)."""

    cores: int = Field(1, ge=1, description="cores per job: 'processes' workers (default: one per core) of cores/processes threads")
    memory: str = Field("4GiB", description="memory per job, e.g. 32GiB; each worker gets memory / processes")
    walltime: str = Field("01:00:00", pattern=r"^\d+:\d{2}:\d{2}$", description="HH:MM:SS")
    queue: Optional[str] = None
    account: Optional[str] = None
    processes: Optional[int] = Field(None, ge=1)
    job_extra_directives: list[str] = Field(default_factory=list)
    minimum_jobs: int = Field(1, ge=0)
    maximum_jobs: int = Field(1, ge=1)
    local_directory: Optional[str] = None
    interface: Optional[str] = None
    python: Optional[str] = None


class ClusterSpec(StrictModel):
    """Where the run computes: ``kind: local`` (default: ``workers``
    single-threaded processes), ``kind: address`` (an existing scheduler at
    ``address``), or ``kind: slurm|pbs|sge`` (workers as batch jobs with the
    resources of ``jobqueue``, through dask-jobqueue). ``scheduler`` is the
    older spelling: an address, or ``synchronous``."""

    kind: Literal["local", "address", "slurm", "pbs", "sge"] = "local"
    address: Optional[str] = Field(None, description="kind address: tcp://host:port", json_schema_extra=option("--scheduler"))
    scheduler: Optional[str] = Field(None, description="None: local cluster; 'threads' (workers threads of one process); 'synchronous'; or tcp://host:port")
    workers: Optional[int] = Field(None, ge=1, json_schema_extra=option("--workers"))
    memory_per_worker: Optional[str] = Field(
        None, description="memory of each worker, e.g. 4GiB (kind local/address; batch jobs: jobqueue.memory)")
    jobqueue: Optional[JobQueueSpec] = None

    @field_validator("memory_per_worker")
    @classmethod
    def _size(cls, value: Optional[str]) -> Optional[str]:
        if value is not None:
            check_size(value, "memory_per_worker", ValueError)
        return value

    @model_validator(mode="after")
    def _consistent(self):
        if self.kind == "address" and not self.address:
            raise ValueError("kind address needs 'address: tcp://host:port'")
        if self.address and self.kind != "address":
            raise ValueError(f"'address' is for kind address, not {self.kind}")
        if self.kind in ("slurm", "pbs", "sge"):
            if self.scheduler:
                raise ValueError(f"a {self.kind} cluster starts its own scheduler: drop 'scheduler'")
            if self.workers is not None:
                raise ValueError(f"a {self.kind} cluster sizes itself from 'jobqueue' (cores, processes, jobs): drop 'workers'")
        elif self.jobqueue is not None:
            raise ValueError(f"'jobqueue' is for kind slurm, pbs or sge, not {self.kind}")
        if self.kind in ("slurm", "pbs", "sge") and self.memory_per_worker is not None:
            raise ValueError(f"a {self.kind} worker's memory is jobqueue.memory / processes: drop 'memory_per_worker'")
        return self

    def config(self, progress: bool = True):
        """The :class:`~tiledsm.cluster.ClusterConfig` of this section."""
        from tiledsm.cluster import ClusterConfig, JobQueueConfig

        if self.kind in ("slurm", "pbs", "sge"):
            jq = (self.jobqueue or JobQueueSpec()).model_dump()
            jq["job_extra_directives"] = tuple(jq["job_extra_directives"])
            return ClusterConfig(jobqueue=JobQueueConfig(kind=self.kind, **jq), progress=progress)
        return ClusterConfig(scheduler=self.address or self.scheduler, workers=self.workers,
                             memory_limit=self.memory_per_worker or "auto", progress=progress)


def load_cluster(path: str | Path) -> ClusterSpec:
    """The ``cluster`` section kept in its own YAML file (``--cluster
    FILE``): either the section's fields, or a mapping with a ``cluster``
    key (a whole recipe works too).

    Raises
    ------
    RecipeError
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise RecipeError(f"{path}: --cluster: cannot read ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: --cluster: not valid YAML ({exc})") from exc
    if isinstance(data, dict) and "cluster" in data:
        data = data["cluster"]
    if not isinstance(data, dict):
        raise RecipeError(f"{path}: --cluster: expected a mapping of cluster fields, got {type(data).__name__}")
    try:
        return ClusterSpec.model_validate(data)
    except ValidationError as exc:
        raise RecipeError(format_errors(path, exc).replace("invalid recipe", "invalid cluster file")) from None


class OutputSpec(StrictModel):
    cog: bool = True
    quicklook: bool = True
    geoid: Optional[str] = Field(None, description="geoid grid (.gtx): write heights above the geoid")


def format_errors(path: Path, exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        parts.append(f"{loc}: {err['msg']}")
    return f"{path}: invalid recipe: " + "; ".join(parts)


#: recipe fields that hold input file paths, wherever they sit: relative ones are resolved against the
#: recipe's folder (:func:`read_recipe`) and every plan checks they exist (outputs such as ``train.out`` are not)
INPUT_KEYS = frozenset({"images", "rpcs", "reference", "like", "geoid", "stable_mask", "pre", "post", "dem", "truth_dh",
                        "truth_mask", "gcps", "check_points", "cameras", "dsm", "truth", "ref", "other", "image",
                        "weights"})
#: recipe fields that hold input folders (resolved too)
_FOLDER_KEYS = frozenset({"data_dirs"})


def _resolve_paths(data: Any, base: Path, key: str | None = None) -> Any:
    """Make relative file paths in path-valued fields relative to ``base``."""
    if isinstance(data, dict):
        return {k: _resolve_paths(v, base, k) for k, v in data.items()}
    if isinstance(data, list):
        return [_resolve_paths(v, base, key) for v in data]
    if key in INPUT_KEYS | _FOLDER_KEYS and isinstance(data, str) and not Path(data).is_absolute():
        return str((base / data).resolve())
    return data


def dump_resolved(recipe: BaseModel, path: str | Path) -> None:
    """Write the resolved recipe (defaults filled in) as YAML, atomically."""
    from tiledsm.io import atomic_path

    text = yaml.safe_dump(recipe.model_dump(mode="json"), sort_keys=False)
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_text(text)


def read_recipe(path: str | Path, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The fields of a recipe file, ``overrides`` applied, relative input
    paths resolved against the recipe's folder (validation is the
    pipeline's: :func:`tiledsm.pipelines.load_recipe`).

    Raises
    ------
    RecipeError
        Unreadable file, invalid YAML, or not a mapping.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise RecipeError(f"{path}: cannot read recipe ({exc.strerror})") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise RecipeError(f"{path}: a recipe is a mapping of fields, got {type(data).__name__}")
    for key, value in (overrides or {}).items():
        data[key] = value
    return _resolve_paths(data, path.parent)
