"""Plans of ``tiledsm ortho`` and ``tiledsm orient``.

Both open every input once (images and their cameras, the DSM, point
files, the reference DEM and geoid), check that the inputs see common
ground, count the tasks, and hand what they opened to the run
(:attr:`Plan.product`), so a typo or a scene that misses the DSM is
refused in seconds, before any cluster starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from tiledsm.errors import InvalidOptionError
from tiledsm.plan.core import MOSTLY_OUTSIDE, InputInfo, Plan, existing_file, new_plan, readable_raster

__all__ = ["plan_ortho", "plan_orient", "PreparedOrientation", "ORTHO_PRODUCTS", "ORIENT_PRODUCTS"]

#: files ``tiledsm ortho`` writes into ``--out`` (the report last)
ORTHO_PRODUCTS = ("ortho.zarr", "ortho.tif", "ortho.png", "ortho.json")
#: files ``tiledsm orient`` writes into ``--out`` besides the images' copies and RPC files
ORIENT_PRODUCTS = ("residuals.csv", "residuals.png", "orient.json")


def plan_ortho(
    image: str,
    dsm: str,
    out: str,
    *,
    kernel: str = "bl",
    resolution: float | None = None,
    chunk: int = 512,
    camera_file: str | None = None,
    bounds: Sequence[float] | None = None,
    crs: str | None = None,
    occlusion: bool = True,
    occlusion_tolerance: float | None = None,
    cluster=None,
) -> Plan:
    """Plan ``tiledsm ortho``: the image (pixels readable) and its camera,
    the DSM (a raster or a tiledsm store), ``--camera``; the lazy ortho
    (:func:`tiledsm.ortho.stage.ortho_files`) is built -- which checks the
    kernel, the resolution, the CRS, ``--bounds`` and that the camera sees
    the DSM -- and its tasks counted; :attr:`Plan.product` is it.

    Warns when the image sees less than half of the ortho grid.

    Returns
    -------
    Plan
    """
    from tiledsm.ortho.stage import ortho_files

    if chunk < 16:
        raise InvalidOptionError(f"--chunk: {chunk} is too small (at least 16 cells)")
    plan = new_plan("ortho", out, cluster)
    img = readable_raster(existing_file(image, "IMAGE"), "IMAGE")
    dsm_path = existing_file(dsm, "--dsm")
    if not dsm_path.endswith(".zarr"):
        readable_raster(dsm_path, "--dsm")
    camera = existing_file(camera_file, "--camera") if camera_file else None
    ortho = ortho_files(
        img, dsm_path, kernel=kernel, resolution=resolution, chunk=chunk, camera_file=camera,
        bounds=tuple(bounds) if bounds is not None else None, crs=crs, occlusion=occlusion,
        occlusion_tolerance=occlusion_tolerance,
    )
    a = ortho.attrs
    plan.inputs.append(InputInfo("IMAGE", img, f"camera: {a.get('camera_source', '?')}"))
    plan.inputs.append(InputInfo("--dsm", dsm_path))
    if camera:
        plan.inputs.append(InputInfo("--camera", camera))
    ny, nx = ortho.shape
    nby, nbx = (len(c) for c in ortho.chunks)
    res = abs(ortho.rio.transform().a)
    plan.grid = (f"{ortho.rio.crs}, {res:g} m cells (DSM cell / {a['factor']}), {ny} x {nx} cells, "
                 f"chunks of {ortho.chunks[0][0]}: {nby} x {nbx} = {nby * nbx}; kernel {a['kernel']}, "
                 f"occlusion halo {a['halo_cells']} DSM cells")
    plan.tasks = len(ortho.data.__dask_graph__())
    seen = float(a["seen_share"])
    if seen < MOSTLY_OUTSIDE:
        plan.warn(f"{img}: IMAGE sees only {seen:.0%} of the ortho grid (the rest is NaN)")
    plan.notes.append(f"the image sees ~{seen:.0%} of the grid (17 x 17 samples at the mid height)")
    plan.notes.append("memory per worker is not estimated for ortho")
    plan.reuse = _replaced(plan.out, ORTHO_PRODUCTS)
    plan.product = ortho
    return plan


@dataclass(frozen=True)
class PreparedOrientation:
    """What an orient plan opened, handed to the run: the images (absolute
    paths), their RPCs and shapes, and the reference DEM (or None)."""

    images: tuple[str, ...]
    rpcs: tuple
    shapes: tuple[tuple[int, int], ...]
    dem: Any = None


def plan_orient(
    images: Sequence[str],
    out: str,
    *,
    gcps: str | None = None,
    check_points: str | None = None,
    dem: str | None = None,
    geoid: str | None = None,
    model: str | None = None,
    tie_points: bool = True,
    tile: int = 512,
    cluster=None,
) -> Plan:
    """Plan ``tiledsm orient``: every image readable with an RPC, distinct
    file stems (their outputs would collide), none inside ``out``; every
    other image sees ground in common with the first (footprint boxes over
    the RPC height range); the point files parse, their measurements fall
    inside their images, and with ``--no-tie-points`` and ``--model`` each
    image has the GCPs the model needs; the DEM (and geoid) covers the
    images. :attr:`Plan.product` is a :class:`PreparedOrientation`.

    Returns
    -------
    Plan
    """
    import math

    from tiledsm.geometry.footprint import overlap_lonlat_bounds
    from tiledsm.io.cameras import find_camera
    from tiledsm.orient.points import ControlPoints, read_points

    if geoid and not dem:
        raise InvalidOptionError("--geoid: only meaningful with --dem")
    if tile < 64:
        raise InvalidOptionError(f"--tile: must be >= 64 pixels, got {tile}")
    if len(images) < 2 and not gcps:
        raise InvalidOptionError("IMAGES: one image needs --gcps (tie points need two or more images)")
    plan = new_plan("orient", out, cluster)
    paths = [readable_raster(existing_file(p, "IMAGES"), "IMAGES") for p in images]
    stems = [Path(p).stem for p in paths]
    if len(set(stems)) != len(stems):
        raise InvalidOptionError(f"IMAGES: two images share a file stem ({', '.join(stems)}); outputs would collide")
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
        plan.inputs.append(InputInfo("IMAGES", p, f"{shape[0]} x {shape[1]} px, RPC from {origin}"))
    h = [(r.height_off - abs(r.height_scale), r.height_off + abs(r.height_scale)) for r in rpcs]
    h_range = (min(a for a, _ in h), max(b for _, b in h))
    for k in range(1, len(paths)):
        overlap_lonlat_bounds(rpcs[0], shapes[0], rpcs[k], shapes[k], h_range)
    counts = None
    for role, path in (("--gcps", gcps), ("--check-points", check_points)):
        if path:
            p = existing_file(path, role)
            pts = read_points(p, paths, shapes)
            plan.inputs.append(InputInfo(role, p, f"{len(pts.point_ids)} points, {len(pts)} image measurements"))
            if role == "--gcps":
                counts = pts.count_per_image(len(paths))
    if model is not None and not tie_points:
        from tiledsm.orient.bias import get_model

        m = get_model(model)
        counts = counts if counts is not None else ControlPoints.empty().count_per_image(len(paths))
        short = [f"{Path(p).name} has {int(c)}" for p, c in zip(paths, counts) if c < m.min_gcps]
        if short:
            raise InvalidOptionError(
                f"--model {m.name}: needs at least {m.min_gcps} GCP measurement(s) per image, but "
                f"{'; '.join(short)} (use --model shift, or add GCPs, or drop --no-tie-points)")
    reference = None
    if dem:
        from tiledsm.orient.dem import ReferenceDEM

        dem_path = readable_raster(existing_file(dem, "--dem"), "--dem")
        geoid_path = existing_file(geoid, "--geoid") if geoid else None
        reference = ReferenceDEM.for_cameras(dem_path, rpcs, shapes, geoid=geoid_path)
        plan.inputs.append(InputInfo("--dem", dem_path, f"{reference.grid.shape[0]} x {reference.grid.shape[1]} "
                                                        "cells read over the images"))
        if geoid_path:
            plan.inputs.append(InputInfo("--geoid", geoid_path))
    if tie_points and len(paths) >= 2:
        nb = math.ceil(shapes[0][0] / tile) * math.ceil(shapes[0][1] / tile)
        plan.grid = (f"tie points: {nb} tiles of {tile} px over {Path(paths[0]).name} "
                     f"({shapes[0][0]} x {shapes[0][1]} px), matched in {len(paths) - 1} other image(s)")
        plan.tasks = nb
    else:
        plan.grid = "no tie points: GCPs only"
        plan.tasks = 0
    plan.height_range = h_range
    plan.notes.append("heights: the RPCs' validity range (the tie points narrow it from overviews)")
    plan.notes.append("memory per worker is not estimated for orient")
    plan.reuse = _replaced(plan.out, ORIENT_PRODUCTS + tuple(f"{s}{e}" for s in stems for e in (".tif", "_RPC.TXT")))
    plan.product = PreparedOrientation(tuple(paths), tuple(rpcs), tuple(shapes), reference)
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

