"""Plans of ``tiledsm sr`` and ``tiledsm compare``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from tiledsm.errors import (
    GridError,
    InputFileError,
    InvalidOptionError,
    NoOverlapError,
)
from tiledsm.plan.core import (
    InputInfo, Plan, existing_file, format_bounds, new_plan, overlap_fraction, raster_header, readable_raster,
)
from tiledsm.plan.dsm import refuse_or_warn
from tiledsm.plan.recipes import polygons_touch, check_sr_weights


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
    overwrite: bool = False,
    **sr_options: Any,
) -> Plan:
    """Plan ``tiledsm sr``: the image and its camera open, the output is a
    GeoTIFF or zarr path in an existing folder, ``model`` has weights at
    ``scale`` (or x2 weights applied repeatedly, or ``weights`` exists),
    an existing OUTPUT is replaced only with ``overwrite``, and the lazy tiled graph
    (:func:`tiledsm.sr.infer.super_resolve` with ``sr_options``: device,
    blur_sigma, noise) is built and counted; :attr:`Plan.product` is it.

    Returns
    -------
    Plan
    """
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
    if out.exists() and not overwrite:
        raise InvalidOptionError(f"{out}: OUTPUT: exists; pass --overwrite to replace it")
    src = readable_raster(existing_file(image, "INPUT"), "INPUT")
    from tiledsm.io import open_scene
    from tiledsm.sr.infer import super_resolve  # imports torch: after the cheap checks

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
        from tiledsm.sr.registry import weight_chain

        if weight_chain(model, scale) is None:  # neither native weights nor x2 weights to apply repeatedly
            check_sr_weights([model], scale, "--scale", "pass --weights FILE (see `tiledsm train-sr`), "
                                                         "a power-of-two scale or --model bicubic")
        net = model
    plan.product = super_resolve(scene, net, scale, **sr_options)
    if plan.product.attrs.get("sr_scheme"):
        plan.notes.append(f"{model} has no native x{scale} weights: its {plan.product.attrs['sr_scheme']} "
                          "(a substitute, recorded in the output's sr_scheme tag)")
    ny, nx = plan.product.sizes["y"], plan.product.sizes["x"]
    nby, nbx = -(-scene.sizes["y"] // chunk), -(-scene.sizes["x"] // chunk)
    plan.grid = f"{ny} x {nx} px output (x{scale}), tiles of {chunk} input px: {nby} x {nbx} = {nby * nbx}"
    plan.tasks = len(plan.product.data.__dask_graph__())
    plan.notes.append("memory per worker is not estimated for SR")
    plan.reuse = f"nothing: {out} is written whole" + (" (replacing the existing one: --overwrite)" if out.exists() else "")
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
        h = raster_header(p, name)
        if h["crs"] is None:
            raise GridError(f"{p}: {name}: has no CRS; a DSM to compare needs one")
        heads[name] = (p, h)
        plan.inputs.append(InputInfo(name, p, f"{h['shape'][0]} x {h['shape'][1]} cells of {h['res']:g}, {h['crs']}"))
    (ref_p, rh), (oth_p, oh) = heads["REF"], heads["OTHER"]
    from tiledsm.compare.align import ReferenceGrid, open_dsm

    # the comparison runs on REF's own grid, geographic CRSs included: no projected DSM grid is made
    grid = ReferenceGrid.of(open_dsm(ref_p, chunks), chunks)
    frac = overlap_fraction(oh["bounds"], oh["crs"], grid)
    refuse_or_warn(plan, frac, NoOverlapError(f"{oth_p}: OTHER: has no ground in common with REF {ref_p}"),
                    f"{oth_p}: OTHER covers only {frac:.0%} of REF's grid")
    plan.grid = grid.describe() + f"; OTHER covers {frac:.0%} of it"
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
        if not polygons_touch(geoms, grid.bounds):
            raise NoOverlapError(f"{mask}: --stable-mask: no polygon lies within REF's extent "
                                 f"{format_bounds(grid.bounds)} ({rh['crs']}): it would exclude nothing")
        if not (excluded & valid).any():
            plan.warn(f"{mask}: --stable-mask excludes no valid cell of REF (sampled every {step} cells)")
    plan.reuse = "nothing: the comparison is recomputed whole (products replaced when all succeeded)"
    return plan
