"""The plan of ``pipeline: orient`` (``tiledsm orient``, ``tiledsm run``).

It opens every input once (the images and their RPCs, the point files, the
reference DEM and geoid), checks that the images see common ground, counts
the tie-point tasks, and hands what it opened to the run
(:attr:`Plan.product`, a :class:`PreparedOrientation`), so a typo or a
scene without common ground is refused in seconds, before any cluster
starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from tiledsm.errors import InvalidOptionError
from tiledsm.orient.recipe import OrientRecipe
from tiledsm.plan.core import (
    RECIPE_NAMES, FieldNames, InputInfo, Plan, check_earlier_run, existing_file, namer, readable_raster,
)

__all__ = ["plan_orient", "PreparedOrientation", "ORIENT_PRODUCTS", "orient_products"]

#: files ``tiledsm orient`` writes into ``--out`` besides the images' copies and RPC files
ORIENT_PRODUCTS = ("residuals.csv", "residuals.png", "orient.json")


def orient_products(images: Sequence[str]) -> tuple[str, ...]:
    """Every file an orientation of ``images`` writes into its folder."""
    return ORIENT_PRODUCTS + tuple(f"{Path(p).stem}{e}" for p in images for e in (".tif", "_RPC.TXT"))


@dataclass(frozen=True)
class PreparedOrientation:
    """What an orient plan opened, handed to the run: the images (absolute
    paths), their RPCs and shapes, the point files (absolute paths or None)
    and the reference DEM (or None)."""

    images: tuple[str, ...]
    rpcs: tuple
    shapes: tuple[tuple[int, int], ...]
    dem: Any = None
    gcps: str | None = None
    check_points: str | None = None


def plan_orient(plan: Plan, recipe: OrientRecipe, cluster=None, *, overwrite: bool = False,
                names: FieldNames = RECIPE_NAMES) -> Plan:
    """Fill ``plan`` (made by :func:`tiledsm.pipelines.plan_recipe`) for a
    ``pipeline: orient`` recipe: every image readable with an RPC, distinct
    file stems (their outputs would collide), none inside the folder; every
    other image sees ground in common with the first (footprint boxes over
    the RPC height range); the point files parse, their measurements fall
    inside their images, and without tie points but with a ``model`` each
    image has the GCPs the model needs; the DEM (and geoid) covers the
    images. :attr:`Plan.product` is a :class:`PreparedOrientation`. An
    orientation is fast: a rerun of the same recipe computes it again, its
    earlier products withdrawn first; a folder holding a run of other
    inputs or options is refused without ``overwrite``
    (:func:`~tiledsm.plan.core.check_earlier_run`, as ``sr`` and
    ``compare``).

    Returns
    -------
    Plan
    """
    import math

    from tiledsm.geometry.footprint import overlap_lonlat_bounds
    from tiledsm.io.cameras import find_camera
    from tiledsm.orient.points import ControlPoints, read_points

    name = namer(OrientRecipe, plan)
    spec, images = recipe.orient, recipe.images
    if len(images) < 2 and not spec.gcps:
        raise InvalidOptionError(f"{name('images')}: one image needs {name('orient.gcps')} "
                                 "(tie points need two or more images)")
    paths = [readable_raster(existing_file(p, name("images")), name("images")) for p in images]
    stems = [Path(p).stem for p in paths]
    if len(set(stems)) != len(stems):
        raise InvalidOptionError(f"{name('images')}: two images share a file stem ({', '.join(stems)}); "
                                 "outputs would collide")
    for p in paths:
        if (plan.out / (Path(p).stem + ".tif")).resolve() == Path(p):
            raise InvalidOptionError(f"--out: {plan.out} holds the input {Path(p).name}; choose another folder")
    rpcs, shapes = [], []
    for p in paths:
        rpc, origin = find_camera(p)
        shape = _shape(p)
        rpcs.append(rpc)
        shapes.append(shape)
        origin = origin.replace(f" of {p}", "")  # the path is the input's own
        plan.inputs.append(InputInfo(name("images"), p, f"{shape[0]} x {shape[1]} px, RPC from {origin}"))
    h = [(r.height_off - abs(r.height_scale), r.height_off + abs(r.height_scale)) for r in rpcs]
    h_range = (min(a for a, _ in h), max(b for _, b in h))
    for k in range(1, len(paths)):
        overlap_lonlat_bounds(rpcs[0], shapes[0], rpcs[k], shapes[k], h_range)
    counts = None
    files: dict[str, str | None] = {}
    for field in ("gcps", "check_points"):
        path, role = getattr(spec, field), name(f"orient.{field}")
        files[field] = None
        if path:
            files[field] = p = existing_file(path, role)
            pts = read_points(p, paths, shapes)
            plan.inputs.append(InputInfo(role, p, f"{len(pts.point_ids)} points, {len(pts)} image measurements"))
            if field == "gcps":
                counts = pts.count_per_image(len(paths))
    if spec.model is not None and not spec.tie_points:
        from tiledsm.orient.bias import get_model

        m = get_model(spec.model)
        counts = counts if counts is not None else ControlPoints.empty().count_per_image(len(paths))
        short = [f"{Path(p).name} has {int(c)}" for p, c in zip(paths, counts) if c < m.min_gcps]
        if short:
            raise InvalidOptionError(
                f"{name('orient.model')} {m.name}: needs at least {m.min_gcps} GCP measurement(s) per image, but "
                f"{'; '.join(short)} (use {name('orient.model')} shift, or add GCPs, or drop "
                f"{name('orient.tie_points')})")
    reference = None
    if spec.dem:
        from tiledsm.orient.dem import ReferenceDEM

        dem_path = readable_raster(existing_file(spec.dem, name("orient.dem")), name("orient.dem"))
        geoid_path = existing_file(spec.geoid, name("orient.geoid")) if spec.geoid else None
        reference = ReferenceDEM.for_cameras(dem_path, rpcs, shapes, geoid=geoid_path)
        plan.inputs.append(InputInfo(name("orient.dem"), dem_path, f"{reference.grid.shape[0]} x "
                                     f"{reference.grid.shape[1]} cells read over the images"))
        if geoid_path:
            plan.inputs.append(InputInfo(name("orient.geoid"), geoid_path))
    if spec.tie_points and len(paths) >= 2:
        nb = math.ceil(shapes[0][0] / spec.tile) * math.ceil(shapes[0][1] / spec.tile)
        plan.grid = (f"tie points: {nb} tiles of {spec.tile} px over {Path(paths[0]).name} "
                     f"({shapes[0][0]} x {shapes[0][1]} px), matched in {len(paths) - 1} other image(s)")
        plan.tasks = nb
    else:
        plan.grid = "no tie points: GCPs only"
        plan.tasks = 0
    plan.height_range = h_range
    plan.notes.append("heights: the RPCs' validity range (the tie points narrow it from overviews)")
    plan.notes.append("memory per worker is not estimated for orient")
    check_earlier_run(recipe, plan.out, overwrite)
    plan.reuse = _replaced(plan.out, orient_products(paths))
    plan.product = PreparedOrientation(tuple(paths), tuple(rpcs), tuple(shapes), reference, files["gcps"],
                                       files["check_points"])
    return plan


def _shape(path: str) -> tuple[int, int]:
    import warnings

    import rasterio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # NotGeoreferencedWarning: RPC images have no geotransform
        with rasterio.open(path) as ds:
            return int(ds.height), int(ds.width)


def _replaced(out: Path, names: Sequence[str]) -> str:
    found = [n for n in names if (out / n).exists()]
    if not found:
        return "nothing (no earlier products in the output folder)"
    return (f"nothing: {', '.join(found)} from an earlier run are withdrawn before the run starts and "
            "written anew")
