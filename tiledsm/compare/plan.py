"""The plan of ``pipeline: compare`` (``tiledsm compare`` and ``tiledsm run``):
both DSMs open with a CRS and overlap, the stable mask reads and lies in
REF's extent, and an earlier run in the folder is one of the same recipe
(or ``--overwrite``)."""

from __future__ import annotations

import math

from tiledsm.errors import GridError, NoOverlapError
from tiledsm.plan.core import (
    InputInfo, Plan, check_earlier_run, existing_file, format_bounds, namer, overlap_fraction, raster_header,
    refuse_or_warn,
)

__all__ = ["plan_compare"]


def plan_compare(plan: Plan, recipe, cluster=None, *, overwrite: bool = False, names=None) -> Plan:
    """Fill ``plan`` (made by :func:`tiledsm.pipelines.plan_recipe`: workers,
    scheduler and the folder's lock checked) for a
    :class:`~tiledsm.compare.recipe.CompareRecipe`.

    Messages name the command's options when ``tiledsm compare`` built the
    recipe (``plan.command``), the recipe's field paths otherwise;
    ``names`` (the DSM stage's spellings) is not used.

    Returns
    -------
    Plan
        ``plan``: inputs, REF's grid and how much of it OTHER covers,
        warnings (little overlap, a mask that excludes no valid cell).

    Raises
    ------
    InputFileError, GridError, NoOverlapError, InvalidOptionError
    """
    import numpy as np

    from tiledsm.compare.recipe import CompareRecipe
    spelled = namer(CompareRecipe, plan)
    inp, spec = recipe.input, recipe.compare
    heads = {}
    for key in ("ref", "other"):
        name = spelled(f"input.{key}")
        p = existing_file(getattr(inp, key), name)
        h = raster_header(p, name)
        if h["crs"] is None:
            raise GridError(f"{p}: {name}: has no CRS; a DSM to compare needs one")
        heads[key] = (p, h)
        plan.inputs.append(InputInfo(name, p, f"{h['shape'][0]} x {h['shape'][1]} cells of {h['res']:g}, {h['crs']}"))
    (ref_p, rh), (oth_p, oh) = heads["ref"], heads["other"]
    from tiledsm.compare.align import ReferenceGrid, open_dsm

    # the comparison runs on REF's own grid, geographic CRSs included: no projected DSM grid is made
    grid = ReferenceGrid.of(open_dsm(ref_p, spec.chunk), spec.chunk)
    frac = overlap_fraction(oh["bounds"], oh["crs"], grid)
    refuse_or_warn(plan, frac, NoOverlapError(f"{oth_p}: {spelled('input.other')}: has no ground in common with "
                                              f"{spelled('input.ref')} {ref_p}"),
                   f"{oth_p}: {spelled('input.other')} covers only {frac:.0%} of {spelled('input.ref')}'s grid")
    plan.grid = grid.describe() + f"; {spelled('input.other')} covers {frac:.0%} of it"
    if spec.stable_mask:
        from affine import Affine

        from tiledsm.compare.stable import exclusion_mask, polygons_touch, read_polygons

        name = spelled("compare.stable_mask")
        mask = existing_file(spec.stable_mask, name)
        geoms = read_polygons(mask, rh["crs"])
        step = max(1, math.ceil(max(grid.shape) / 1000))
        import rasterio

        with rasterio.open(ref_p) as src:  # decimated by GDAL: the plan never reads the whole grid
            valid = np.isfinite(src.read(1, out_shape=(-(-grid.height // step), -(-grid.width // step)),
                                         masked=True).filled(np.nan).astype(float))
        t = grid.transform @ Affine.scale(grid.width / valid.shape[1], grid.height / valid.shape[0])
        excluded = exclusion_mask(geoms, t, valid.shape) if geoms else np.zeros(valid.shape, bool)
        plan.inputs.append(InputInfo(name, mask, f"{len(geoms)} polygons, exclude {(excluded & valid).mean():.1%} "
                                                 f"of {spelled('input.ref')}'s cells"))
        if not polygons_touch(geoms, grid.bounds):
            raise NoOverlapError(f"{mask}: {name}: no polygon lies within {spelled('input.ref')}'s extent "
                                 f"{format_bounds(grid.bounds)} ({rh['crs']}): it would exclude nothing")
        if not (excluded & valid).any():
            plan.warn(f"{mask}: {name} excludes no valid cell of {spelled('input.ref')} (sampled every {step} cells)")
    check_earlier_run(recipe, plan.out, overwrite)
    plan.reuse = ("nothing: the comparison is recomputed whole; its products are replaced when all succeeded "
                  "(a killed run leaves them as they were)")
    return plan
