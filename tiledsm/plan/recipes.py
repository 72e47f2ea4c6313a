"""Plans of whole recipes (every stage planned before the first runs)."""

from __future__ import annotations

import os
from typing import Any, Sequence

from tiledsm.errors import InvalidOptionError, NoOverlapError
from tiledsm.plan.core import FieldNames, InputInfo, Limits, Plan, RECIPE_NAMES, existing_file, new_plan


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
    and the folder's lock first, then the plan of the recipe's pipeline
    (:attr:`tiledsm.pipelines.Pipeline.plan`, e.g. :func:`tiledsm.plan.plan_dsm`); for
    a pipeline without one (``sr_dsm``, ``deformation``, ``train_sr``) the
    checks that need no stage to run -- inputs exist, SR weights exist for
    ``sr.scale``, a stable mask overlaps the scene -- while their stages
    plan their own grids when they run."""
    from tiledsm.pipelines import PIPELINES

    plan = new_plan(command, out, cluster, limits=limits, workers=names.workers, scheduler=names.scheduler)
    stage_plan = PIPELINES[recipe.pipeline].plan
    if stage_plan is not None:
        return stage_plan(plan, recipe, cluster, overwrite=overwrite, names=names)
    plan.notes.append(f"pipeline {recipe.pipeline}: each stage plans its grid, graph and memory when it runs")
    plan.reuse = "stores of an earlier run with the same fingerprint (checked by each stage)"
    return check_recipe_inputs(plan, recipe)


def check_recipe_inputs(plan: Plan, recipe) -> Plan:
    """The checks of a recipe that need no stage to run: its input files
    exist, SR weights exist for ``sr.scale``, a stable mask overlaps the
    pre-event views."""
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
_INPUT_KEYS = {"images", "rpcs", "reference", "like", "geoid", "stable_mask", "dem", "truth_dh", "truth_mask",
               "cameras", "dsm", "truth"}


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
    if not polygons_touch(read_polygons(mask, "EPSG:4326"), (lon0, lat0, lon1, lat1)):
        raise NoOverlapError(
            f"{mask}: {name}: no polygon lies in the scene the images see (lon/lat box "
            f"({lon0:.5f}, {lat0:.5f}, {lon1:.5f}, {lat1:.5f})): it would exclude nothing"
        )


def polygons_touch(geoms: list[dict], box: Sequence[float]) -> bool:
    """Whether any GeoJSON polygon's bounding box meets ``box``
    ``(xmin, ymin, xmax, ymax)`` (same CRS)."""
    import numpy as np

    for g in geoms:
        rings = g["coordinates"] if g["type"] == "Polygon" else [r for p in g["coordinates"] for r in p]
        xy = np.concatenate([np.asarray(r, float)[:, :2] for r in rings])
        if xy[:, 0].min() <= box[2] and xy[:, 0].max() >= box[0] and xy[:, 1].min() <= box[3] and xy[:, 1].max() >= box[1]:
            return True
    return False


