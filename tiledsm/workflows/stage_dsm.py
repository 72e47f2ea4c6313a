"""A pipeline's DSM made by the DSM stage itself.

``deformation`` (``pre/``, ``post/``) and ``sr_dsm`` (``hr/``, ``lr/``,
one folder per method) make each of their DSMs as a ``pipeline: dsm``
recipe (:class:`tiledsm.workflows.dsm.DSMRecipe`) into its own sub-folder:
planned by :func:`tiledsm.dsm.plan.plan_dsm` (memory-fitted chunk, size
limits, every input opened and checked once) and written by
:func:`tiledsm.workflows.dsm.run_dsm` (resumable fingerprinted
``dsm.zarr``, exports, the folder's own ``metrics.json`` and
``recipe.resolved.yaml``) -- what ``tiledsm dsm`` does.

A synthetic scene does not exist when a run is planned:
:func:`plan_unmade_dsm` plans its DSM from the scene's parameters (its
truth grid and fitted cameras, :func:`tiledsm.synth.layout.scene_layout`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from tiledsm.plan.core import Limits, Plan
from tiledsm.recipes import GridSpec, InputSpec, MatchSpec, OutputSpec
from tiledsm.workflows.dsm import DSMRecipe

__all__ = ["dsm_recipe", "grid_spec", "plan_stage_dsm", "run_stage_dsm", "add_stages", "stage_report", "synthetic_views", "plan_unmade_dsm",
           "scene_heights", "SYNTH_ITEMSIZE"]

#: bytes per pixel of a synthetic scene's images (uint16, :func:`tiledsm.synth.make_scene`)
SYNTH_ITEMSIZE = 2


def dsm_recipe(name: str, images: Sequence[str], rpcs, grid: GridSpec, match: MatchSpec, output: OutputSpec,
               cluster=None) -> DSMRecipe:
    """The ``pipeline: dsm`` recipe of one of a pipeline's DSMs (exports as
    ``output`` says; heights stay ellipsoidal)."""
    data = {"pipeline": "dsm", "name": name, "input": InputSpec(images=[str(i) for i in images], rpcs=rpcs),
            "grid": grid, "match": match, "output": OutputSpec(cog=output.cog, quicklook=output.quicklook)}
    if cluster is not None:
        data["cluster"] = cluster
    return DSMRecipe(**data)


def grid_spec(grid, chunk: int | None = None) -> GridSpec:
    """A recipe ``grid`` section naming exactly ``grid`` (a
    :class:`~tiledsm.geometry.grid.GroundGrid` whose edges lie on multiples
    of its resolution, as the DSM stage's grids do)."""
    return GridSpec(crs=grid.crs, resolution=grid.resolution, bounds=tuple(float(b) for b in grid.bounds),
                    chunk=chunk or grid.chunk)


def plan_stage_dsm(recipe: DSMRecipe, folder: Path, cluster=None, *, overwrite: bool = False,
                   limits: Limits = Limits()) -> Plan:
    """The DSM stage's plan of ``recipe`` into ``folder`` (as ``tiledsm run``
    plans a ``dsm`` recipe: workers and the folder's lock, then
    :func:`tiledsm.dsm.plan.plan_dsm`'s checks, grid, memory-fitted chunk,
    levels and reuse)."""
    from tiledsm.plan.core import RECIPE_NAMES, new_plan
    from tiledsm.dsm.plan import plan_dsm

    plan = new_plan("run", folder, cluster, limits=limits, workers=RECIPE_NAMES.workers,
                    scheduler=RECIPE_NAMES.scheduler)
    return plan_dsm(plan, recipe, cluster, overwrite=overwrite, names=RECIPE_NAMES)


def run_stage_dsm(plan: Plan, recipe: DSMRecipe, folder: Path, cluster, *, overwrite: bool = False) -> dict:
    """Run a planned DSM into ``folder`` as ``tiledsm run`` runs a ``dsm``
    recipe: stale descriptions withdrawn, the store computed or resumed,
    exports, ``metrics.json``, then ``recipe.resolved.yaml``. Returns its
    metrics."""
    from tiledsm.recipes import dump_resolved
    from tiledsm.workflows.common import withdraw_products
    from tiledsm.workflows.dsm import run_dsm

    recipe = plan.recipe or recipe  # a chunk side the plan chose to fit a worker's memory
    folder.mkdir(parents=True, exist_ok=True)
    withdraw_products(folder, recipe, plan, overwrite)
    metrics = run_dsm(recipe, folder, cluster, overwrite=overwrite, plan=plan)
    dump_resolved(recipe, folder / "recipe.resolved.yaml")
    return metrics


def add_stages(plan: Plan, stages: list[tuple[str, Plan]], reuse: str) -> Plan:
    """Give a pipeline's ``plan`` the plans of its DSMs (:attr:`Plan.stages`),
    their warnings and notes (each prefixed by the DSM's name) and ``reuse``."""
    plan.stages = stages
    for name, stage in stages:
        plan.warnings += [f"{name}: {w}" for w in stage.warnings]
        plan.notes += [f"{name}: {n}" for n in stage.notes]
    plan.reuse = reuse
    return plan


def stage_report(metrics: dict) -> dict:
    """What a pipeline's ``metrics.json`` keeps of one DSM's metrics."""
    report = metrics["report"]
    return {"height_range_m": report.get("height_range_m"), "grid": report.get("grid"),
            "completeness": metrics.get("completeness"), "timings": metrics.get("timings")}


def synthetic_views(layout, cameras, paths: Sequence[Path], *, first_view: int = 0) -> list:
    """The views a synthetic scene will have at ``paths`` (not written yet):
    the RPCs :func:`tiledsm.synth.make_scene` fits to ``cameras`` (view
    numbers from ``first_view``: 100 for post-event views)."""
    from tiledsm.dsm.views import View
    from tiledsm.synth.layout import fit_view

    size = layout.grid.width
    return [View(str(path), fit_view(cam, layout.height_range, first_view + i)[0], (size, size))
            for i, (cam, path) in enumerate(zip(cameras, paths))]


def plan_unmade_dsm(folder: Path, views, h_range: tuple[float, float], recipe: DSMRecipe, *, itemsize: int,
                    default_grid=None, limits: Limits = Limits(), reuse: str = "") -> tuple[Plan, object]:
    """The plan of a DSM whose images a run makes first (a synthetic scene,
    an LR or SR pair): ``views`` carry the cameras they will have,
    ``itemsize`` their bytes per pixel, ``h_range`` the heights expected.

    The grid is the recipe's (``like``/``bounds``), else ``default_grid``
    with the recipe's chunk, else the DSM stage's default grid of the
    views. Levels and worker memory are :func:`tiledsm.dsm.memory.dsm_levels`'s;
    the run plans the DSM again (tie points, chunk fitted to a worker's
    memory) once the images exist.

    Returns
    -------
    (Plan, GroundGrid)
        The plan (grid, heights, levels, memory; nothing prepared) and its grid.
    """
    import dataclasses

    from tiledsm.dsm import DSMParams, auto_levels, default_grid as views_grid
    from tiledsm.dsm.plan import grid_text
    from tiledsm.dsm.memory import dsm_levels
    from tiledsm.recipes import grid_from_spec

    spec = recipe.grid
    params = DSMParams.of_recipe(spec, recipe.match)
    if params.height_range is not None:
        h_range = tuple(params.height_range)
    grid = grid_from_spec(spec)
    if grid is None and spec.resolution is None and default_grid is not None:
        grid = dataclasses.replace(default_grid, chunk=spec.chunk)
    elif grid is None:
        grid = views_grid(views, h_range, params)
    nby, nbx = grid.numblocks
    limits.check(grid.width * grid.height, nby * nbx,
                 f"{folder.name}: the DSM grid would be {grid.height:,} x {grid.width:,} cells of {grid.resolution:g} m",
                 "choose smaller inputs (input.synth.size) or a larger grid.chunk")
    plan = Plan("run", folder, limits=limits)
    plan.height_range = h_range
    plan.grid = grid_text(grid)
    levels = params.levels or auto_levels(views, grid, h_range, params)
    plan.levels, plan.memory = dsm_levels(views, grid, h_range, levels, params, itemsize=itemsize)
    plan.reuse = reuse or "decided once its images are made (heights from their tie points, chunk fitted to a " \
                          "worker's memory)"
    return plan, grid


def scene_heights(layout, match) -> tuple[float, float]:
    """The heights a synthetic scene's DSM is expected to span: its terrain
    with ``match.height_margin`` (metres)."""
    lo, hi = layout.height_range
    return (lo - match.height_margin, hi + match.height_margin)
