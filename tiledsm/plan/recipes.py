"""Plans of whole recipes (every stage planned before the first runs)."""

from __future__ import annotations

from typing import Any, Sequence

from tiledsm.errors import NoOverlapError
from tiledsm.compare.stable import polygons_touch
from tiledsm.recipes import INPUT_KEYS
from tiledsm.plan.core import FieldNames, InputInfo, Plan, RECIPE_NAMES, existing_file
from tiledsm.sr.plan import check_sr_weights


# --------------------------------------------------------------------------- recipes
def plan_inputs(plan: Plan, recipe, cluster=None, *, overwrite: bool = False,
                names: FieldNames = RECIPE_NAMES) -> Plan:
    """Fill ``plan`` for a pipeline without a plan of its own
    (:attr:`tiledsm.pipelines.Pipeline.plan`): the checks that need no
    stage to run -- every input file exists, SR weights exist for
    ``sr.scale``, a stable mask overlaps the scene -- while the stages
    plan their own grids when they run."""
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


def _recipe_files(data: Any, where: str) -> list[tuple[str, str]]:
    """``(field path, file)`` of every input file a recipe names."""
    if isinstance(data, dict):
        return [x for k, v in data.items() for x in _recipe_files(v, f"{where}.{k}" if where else k)]
    if isinstance(data, list):
        return [x for v in data for x in _recipe_files(v, where)]
    key = where.rsplit(".", 1)[-1]
    return [(where, data)] if key in INPUT_KEYS and isinstance(data, str) else []


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
