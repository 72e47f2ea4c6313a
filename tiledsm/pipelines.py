"""The pipelines: one registry of what ``pipeline:`` may name in a recipe.

Each pipeline is a workflow module (:mod:`tiledsm.workflows`) or a stage
package (``tiledsm.sr``, ``tiledsm.compare``, ``tiledsm.ortho``, ``tiledsm.orient``: its ``recipe``, ``plan`` and
``run`` modules) holding its recipe model and its runner; :data:`PIPELINES` lists them, explicitly, and
is the only list: :func:`load_recipe` validates a recipe against the
model its ``pipeline`` names, :func:`run_recipe` plans it, locks the run
folder and calls the runner. A runner takes a validated recipe and a run
folder and leaves there the stores, the products,
``recipe.resolved.yaml``, ``metrics.json`` and ``run.log``.

To add a pipeline: write ``tiledsm/workflows/<name>.py`` with a recipe
model (``pipeline: Literal["<name>"]``, deriving from
:class:`tiledsm.recipes.StrictModel`) and ``run_<name>(recipe, out,
cluster, overwrite=False)``, and add one line to :data:`PIPELINES`.
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pydantic import BaseModel, ValidationError

from tiledsm.cluster import ClusterConfig
from tiledsm.compare.plan import plan_compare
from tiledsm.compare.recipe import CompareRecipe
from tiledsm.compare.run import run_compare
from tiledsm.errors import RecipeError
from tiledsm.dsm.plan import plan_dsm
from tiledsm.orient.plan import plan_orient
from tiledsm.orient.run import run_orient
from tiledsm.orient.recipe import OrientRecipe
from tiledsm.ortho.plan import plan_ortho
from tiledsm.ortho.run import run_ortho
from tiledsm.ortho.recipe import OrthoRecipe
from tiledsm.recipes import dump_resolved, format_errors, read_recipe
from tiledsm.sr.plan import plan_sr
from tiledsm.sr.recipe import SRRecipe
from tiledsm.sr.run import run_sr
from tiledsm.workflows.common import setup_log, withdraw_products
from tiledsm.workflows.deformation import DeformationRecipe, plan_deformation, run_deformation
from tiledsm.workflows.displace import DisplaceRecipe, run_displace
from tiledsm.workflows.dsm import DSMRecipe, run_dsm
from tiledsm.workflows.ortho_sr import OrthoSRRecipe, run_ortho_sr
from tiledsm.workflows.sr_dsm import SRDSMRecipe, plan_sr_dsm, run_sr_dsm
from tiledsm.workflows.train_sr import TrainSRRecipe, run_train_sr

log = logging.getLogger("tiledsm")

__all__ = ["Pipeline", "PIPELINES", "load_recipe", "plan_recipe", "run_recipe"]


@dataclass(frozen=True)
class Pipeline:
    """A recipe model, the function that runs it and, where the stage plans
    more than the checks every recipe gets, the function that plans it.

    ``plan(plan, recipe, cluster, *, overwrite, names)`` fills the
    :class:`~tiledsm.plan.Plan` that :func:`plan_recipe`
    made (workers, scheduler and the folder's lock already checked) and
    returns it; ``names`` (:class:`~tiledsm.plan.FieldNames`) says how the
    user spelled each input (command options or recipe fields)."""

    recipe: type[BaseModel]
    run: Callable[..., dict]
    plan: Callable[..., Any] | None = None


#: every pipeline a recipe may name
PIPELINES: dict[str, Pipeline] = {
    "dsm": Pipeline(DSMRecipe, run_dsm, plan=plan_dsm),
    "sr_dsm": Pipeline(SRDSMRecipe, run_sr_dsm, plan=plan_sr_dsm),
    "deformation": Pipeline(DeformationRecipe, run_deformation, plan=plan_deformation),
    "ortho_sr": Pipeline(OrthoSRRecipe, run_ortho_sr),
    "train_sr": Pipeline(TrainSRRecipe, run_train_sr),
    "displace": Pipeline(DisplaceRecipe, run_displace),
    "sr": Pipeline(SRRecipe, run_sr, plan=plan_sr),
    "compare": Pipeline(CompareRecipe, run_compare, plan=plan_compare),
    "ortho": Pipeline(OrthoRecipe, run_ortho, plan=plan_ortho),
    "orient": Pipeline(OrientRecipe, run_orient, plan=plan_orient),
}


def load_recipe(path: str | Path, overrides: dict[str, Any] | None = None) -> BaseModel:
    """Read a recipe file and validate it against its pipeline's model.

    Relative input paths are resolved against the recipe's folder.

    Raises
    ------
    RecipeError
        Unreadable YAML, unknown pipeline, or a field that fails the schema
        (the message lists each field path and what was expected).
    """
    data = read_recipe(path, overrides)
    name = data.get("pipeline")
    if not isinstance(name, str) or name not in PIPELINES:  # a list (`pipeline: [dsm]`) is not hashable
        kind = "" if name is None or isinstance(name, str) else f" (a {type(name).__name__}; one name is expected)"
        raise RecipeError(f"{path}: pipeline: expected one of {sorted(PIPELINES)}, got {name!r}{kind}")
    try:
        return PIPELINES[name].recipe.model_validate(data)
    except ValidationError as exc:
        raise RecipeError(format_errors(Path(path), exc)) from None


def plan_recipe(
    recipe,
    out: str | Path,
    cluster: ClusterConfig | None = None,
    *,
    overwrite: bool = False,
    limits=None,
    names=None,
    command: str = "run",
):
    """Plan any recipe into the folder ``out`` (made absolute): the workers,
    the scheduler and the folder's lock first (:func:`tiledsm.plan.new_plan`),
    then the plan of the recipe's pipeline (:attr:`Pipeline.plan`, e.g.
    :func:`tiledsm.dsm.plan.plan_dsm`), or, for a pipeline without one, the
    checks every recipe gets (:func:`tiledsm.plan.plan_inputs`).

    ``names`` (:class:`~tiledsm.plan.FieldNames`, default the recipe's
    field paths) says how the user spelled each input; ``command`` heads
    the plan's summary."""
    from tiledsm.plan import RECIPE_NAMES, Limits, new_plan, plan_inputs

    names = names or RECIPE_NAMES
    plan = new_plan(command, out, cluster, limits=limits or Limits(), workers=names.workers, scheduler=names.scheduler)
    stage_plan = PIPELINES[recipe.pipeline].plan or plan_inputs
    return stage_plan(plan, recipe, cluster, overwrite=overwrite, names=names)


def run_recipe(
    recipe,
    out_dir: str | Path,
    cluster: ClusterConfig | None = None,
    overwrite: bool = False,
    *,
    plan=None,
    limits=None,
) -> dict:
    """Run a validated recipe into ``out_dir``; returns its metrics.

    The run is planned first (:func:`plan_recipe`, unless
    ``plan`` is given): what cannot work is refused in seconds, before the
    folder is created, locked or any cluster started. The folder is then
    locked for the run (:class:`tiledsm.io.lock.OutputLock`: a second
    run into it stops at once). Stores finished or left partial by an
    earlier run are resumed only when their fingerprint (inputs, RPCs,
    grid, parameters, code) equals this run's; otherwise the run stops
    naming what changed, unless ``overwrite``.

    ``metrics.json`` and ``recipe.resolved.yaml`` describe the products
    beside them: when the products are going to change (``overwrite``,
    another resolved recipe, a DSM store to compute or complete) both are
    withdrawn (with the DSM's exports) before anything is computed, and
    written again last, when the products are complete. So no
    interruption -- before the store exists, while it fills, after it is
    finished -- leaves them claiming products they do not describe.
    """
    from tiledsm.plan import Limits
    from tiledsm.io.lock import OutputLock

    out = Path(out_dir).expanduser().resolve()
    if plan is None:
        plan = plan_recipe(recipe, out, cluster, overwrite=overwrite, limits=limits or Limits())
    recipe = plan.recipe or recipe  # e.g. a chunk side the plan chose to fit a worker's memory
    out.mkdir(parents=True, exist_ok=True)
    with OutputLock(out):
        handler = setup_log(out)
        try:
            log.info("running pipeline %s into %s (overwrite: %s)", recipe.pipeline, out, overwrite)
            for message in plan.warnings:
                log.warning(message)
            withdraw_products(out, recipe, plan, overwrite)
            runner = PIPELINES[recipe.pipeline].run
            extra = {"plan": plan} if "plan" in inspect.signature(runner).parameters else {}
            metrics = runner(recipe, out, cluster, overwrite=overwrite, **extra)
            dump_resolved(recipe, out / "recipe.resolved.yaml")
            return metrics
        finally:
            logging.getLogger("tiledsm").removeHandler(handler)
            handler.close()
