"""The plan of ``pipeline: ortho`` (``tiledsm ortho``, ``tiledsm run``).

It opens every input once (the image and its camera, the DSM, the camera
file), builds the lazy ortho (which checks the kernel, the resolution, the
CRS, the bounds and that the camera sees the DSM), counts its tasks, takes
its fingerprint and says what of an earlier run in the folder is reused:
a typo, a scene that misses the DSM or a store of other inputs is refused
in seconds, before any cluster starts. :attr:`Plan.product` is the lazy
ortho, fingerprint in its attrs, which the run computes.
"""

from __future__ import annotations

import json
from pathlib import Path

from tiledsm.ortho.recipe import OrthoRecipe
from tiledsm.plan.core import (
    MOSTLY_OUTSIDE, RECIPE_NAMES, FieldNames, InputInfo, Plan, existing_file, readable_raster, namer,
)

__all__ = ["plan_ortho", "ORTHO_STORE", "ORTHO_EXPORTS"]

#: the resumable store of the ortho, in the run folder
ORTHO_STORE = "ortho.zarr"
#: files written from the finished store (the report last)
ORTHO_EXPORTS = ("ortho.tif", "ortho.png", "ortho.json")


def plan_ortho(plan: Plan, recipe: OrthoRecipe, cluster=None, *, overwrite: bool = False,
               names: FieldNames = RECIPE_NAMES) -> Plan:
    """Fill ``plan`` (made by :func:`tiledsm.pipelines.plan_recipe`) for a
    ``pipeline: ortho`` recipe: the image (pixels readable) and its camera,
    the DSM (a raster or a tiledsm store), the camera file; the lazy ortho
    (:func:`tiledsm.ortho.stage.ortho_files`) built and its tasks counted;
    its fingerprint (:func:`tiledsm.ortho.stage.ortho_fingerprint`) set in
    its attrs; an earlier ``ortho.zarr`` (finished or partial) checked
    against it (:func:`ortho_reuse`).

    Warns when the image sees less than half of the ortho grid.

    Raises
    ------
    FingerprintMismatchError
        The folder holds an ortho store of other inputs or parameters, and
        not ``overwrite``.
    """
    from tiledsm.ortho.stage import ortho_files, ortho_fingerprint

    name = namer(OrthoRecipe, plan)
    inp, grid, spec = recipe.input, recipe.grid, recipe.ortho
    img = readable_raster(existing_file(inp.image, name("input.image")), name("input.image"))
    dsm_path = existing_file(inp.dsm, name("input.dsm"))
    if not dsm_path.endswith(".zarr"):
        readable_raster(dsm_path, name("input.dsm"))
    camera = existing_file(inp.camera, name("input.camera")) if inp.camera else None
    ortho = ortho_files(img, dsm_path, spec, resolution=grid.resolution, chunk=grid.chunk, camera_file=camera,
                        bounds=grid.bounds, crs=grid.crs)
    a = ortho.attrs
    plan.inputs.append(InputInfo(name("input.image"), img, f"camera: {a.get('camera_source', '?')}"))
    plan.inputs.append(InputInfo(name("input.dsm"), dsm_path))
    if camera:
        plan.inputs.append(InputInfo(name("input.camera"), camera))
    ny, nx = ortho.shape
    nby, nbx = (len(c) for c in ortho.chunks)
    res = abs(ortho.rio.transform().a)
    plan.grid = (f"{ortho.rio.crs}, {res:g} m cells (DSM cell / {a['factor']}), {ny} x {nx} cells, "
                 f"chunks of {ortho.chunks[0][0]}: {nby} x {nbx} = {nby * nbx}; kernel {a['kernel']}, "
                 f"occlusion halo {a['halo_cells']} DSM cells")
    plan.tasks = len(ortho.data.__dask_graph__())
    seen = float(a["seen_share"])
    if seen < MOSTLY_OUTSIDE:
        plan.warn(f"{img}: {name('input.image')} sees only {seen:.0%} of the ortho grid (the rest is NaN)")
    plan.notes.append(f"the image sees ~{seen:.0%} of the grid (17 x 17 samples at the mid height)")
    plan.notes.append("memory per worker is not estimated for ortho")
    fp = ortho_fingerprint(ortho, img, dsm_path, camera, spec)
    ortho.attrs["fingerprint"] = json.dumps(fp, sort_keys=True)
    plan.reuse, plan.withdraw = ortho_reuse(plan.out, ortho, fp, overwrite)
    plan.product = ortho
    return plan


def ortho_reuse(out: Path, ortho, fingerprint: dict, overwrite: bool) -> tuple[str, bool]:
    """What of ``out/ortho.zarr`` (finished) or ``out/ortho.zarr.partial``
    a run would reuse, and whether the store will change.

    Raises
    ------
    FingerprintMismatchError
        The stored ortho was computed from other inputs or parameters and
        not ``overwrite`` (the message the run itself would give).
    """
    from tiledsm.io import ChunkStore
    from tiledsm.plan.core import store_reuse

    chunk = int(ortho.chunks[0][0]), int(ortho.chunks[1][0])
    store = ChunkStore(str(out / ORTHO_STORE), ("ortho",), tuple(ortho.shape), chunk)
    return store_reuse(store, "ortho", fingerprint, overwrite)
