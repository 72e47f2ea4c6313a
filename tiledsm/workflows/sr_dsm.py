"""Super-resolution before matching: the SR -> DSM comparison workflow (see tiledsm.workflows).

The simulated experiment of Zhang et al., "CNN-based subpixel DSM
generation via single-image super-resolution" (issue 4's seed paper): a
high-resolution (HR) stereo pair is degraded to a low-resolution (LR) pair,
and DSMs made from the LR pair with and without super-resolution are
compared with the DSM of the HR pair.

Steps (``pipeline: sr_dsm``), all under the run folder:

1. ``scene/`` (synthetic input only): the HR pair and its truth
   (:func:`tiledsm.synth.make_scene`).
2. ``hr/``: the reference DSM, from the HR pair, on the ground grid ``G``
   (HR resolution). ``G`` is, in order: ``grid.like``; the grid of
   ``input.reference``; the grid of the synthetic truth; ``grid.bounds``;
   else the HR DSM's own default grid.
3. ``lr/``: the LR pair (:func:`tiledsm.synth.degrade`, ``sr.degrade``
   kernel, factor ``sr.scale``, RPCs regenerated exactly) and, for the
   ``dsm_upscale`` method, its DSM on ``G`` coarsened ``sr.scale`` times
   (:func:`lr_grid`).
4. one folder per method (``sr.models``):

   - ``dsm_upscale/``: the LR DSM interpolated bilinearly onto ``G``
     (:func:`upsample_dsm`);
   - ``bicubic/``, ``srcnn/``, ``vdsr/``, ``srmd/``, ``srmd_official/``
     (the authors' published weights, :mod:`tiledsm.sr.ncnn`): each LR image
     super-resolved ``sr.scale`` times (:func:`tiledsm.sr.super_resolve`,
     shipped weights, RPC scaled), written as ``sr_view_{i}.tif``
     (float32 DN with RPC tags), then its DSM on ``G``.

5. ``metrics.json`` and ``report.md``: image quality of each SR image
   against the HR image (PSNR, SSIM; Table 1 of the paper) and each DSM's
   report.

The DSM accuracy (RMSE, MRE, NMAD, completeness; Table 2) against the
HR-pair DSM, plus against the synthetic truth on visible ground or the
given reference DSM when there is one (Tables 3 and 4), is not the run's:
``tiledsm evaluate OUT`` writes it (:mod:`tiledsm.evaluate.sr_dsm`) into
``OUT/evaluation.json``, ``OUT/evaluation/report.md`` (Tables 1-4) and
``OUT/evaluation/blunders.png``.

The DSMs of one table are compared on the same cells: the accuracy
statistics of every DSM are computed on the *common* cells, where the
reference and every compared DSM have a height (:func:`compare_on_common`),
so a method cannot look better by leaving holes where matching is hard.
Each DSM's own completeness (its share of the reference's cells) is
reported beside them, and the common cells' count and share in
``metrics.json`` (``common``) and under each table.

Conventions
-----------
- Heights are metres above the WGS84 ellipsoid; NaN = no height.
- Pixel grids follow GDAL's corner convention: LR pixel ``j`` covers HR
  pixels ``[j s, (j + 1) s)``; SR pixel ``k`` covers LR area
  ``[k / s, (k + 1) / s)``; so an SR image is registered to its HR image
  pixel for pixel (HR images are cropped to ``s * floor(n / s)``).
- PSNR/SSIM peak: ``2**sr.bit_depth - 1`` DN; ``sr.border`` pixels
  (default ``sr.scale``) are cropped on each side.
- MRE is the mean of ``|dh| / |h_ref|`` (ellipsoidal heights), reported
  in percent.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
import xarray as xr
from scipy import sparse
from pydantic import Field, field_validator, model_validator

from tiledsm.cluster import ClusterConfig, compute_context, shared_cluster
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.recipes import (
    ClusterSpec,
    GridSpec,
    InputSpec,
    MatchSpec,
    OutputSpec,
    StrictModel,
)
from tiledsm.synth.degrade import gaussian_sigma
from tiledsm.workflows.sr_scores import SRDSMError, markdown_report

log = logging.getLogger("tiledsm")

__all__ = [
    "METHODS",
    "UPSCALE",
    "SRSpec",
    "SRDSMRecipe",
    "SRDSMError",
    "lr_grid",
    "upsample_dsm",
    "run_sr_dsm",
]

#: the method that super-resolves the DSM instead of the images
UPSCALE = "dsm_upscale"
#: every method, in the order of the paper's tables
METHODS = (UPSCALE, "bicubic", "srcnn", "vdsr", "srmd", "srmd_official")


# ------------------------------------------------------------------ schema
class SRSpec(StrictModel):
    """Degradation and super-resolution settings of ``pipeline: sr_dsm``."""

    scale: int = Field(2, ge=2, le=4, description="HR/LR factor; the SR factor too")
    models: list[str] = Field(default_factory=lambda: list(METHODS), min_length=1,
                              description=f"methods to run, among {list(METHODS)} (and any registered SR model)")
    degrade: Literal["bicubic", "gaussian"] = Field("bicubic", description="LR kernel (tiledsm.synth.degrade)")
    degrade_sigma: Optional[float] = Field(None, gt=0, description="gaussian kernel sigma, HR px (default scale / 2)")
    lr_noise: float = Field(0.0, ge=0, description="noise added to the LR images, DN (std)")
    bit_depth: int = Field(12, ge=8, le=16, description="sensor bit depth: PSNR peak (and SR normalisation if full_scale)")
    normalisation: Literal["stretch", "full_scale"] = Field(
        "stretch", description="value mapped to 1 before the SR networks: each LR image's 99.9th percentile "
                               "(stretch) or 2**bit_depth - 1 (full_scale); tiledsm.sr.infer.NORMALISATIONS")
    srmd_blur_sigma: Union[Literal["bicubic"], Annotated[float, Field(ge=0)], None] = Field(
        None,
        description="SRMD's blur: a Gaussian sigma in HR px, or 'bicubic' (the shipped SRMD was trained with the "
                    "bicubic kernel too); default: the degradation that made the LR pair ('bicubic', or the "
                    "gaussian's sigma)")
    srmd_noise: float = Field(0.0, ge=0, description="SRMD's noise level, DN (std)")
    chunk: int = Field(256, ge=32, description="SR tile side, LR pixels")
    border: Optional[int] = Field(None, ge=0, description="pixels cropped for PSNR/SSIM (default: scale)")
    device: str = Field("cpu", description="torch device of the SR networks")

    @model_validator(mode="after")
    def _srmd_told_the_degradation(self):
        if self.srmd_blur_sigma is None:
            sigma = "bicubic" if self.degrade == "bicubic" else gaussian_sigma(self.scale, self.degrade_sigma)
            object.__setattr__(self, "srmd_blur_sigma", sigma)
        return self

    @field_validator("models")
    @classmethod
    def _known_models(cls, value: list[str]) -> list[str]:
        from tiledsm.sr.registry import MODELS

        known = [UPSCALE, *MODELS.names()]
        bad = [m for m in value if m not in known]
        if bad:
            raise ValueError(f"unknown method(s) {bad}; known: {known}")
        if len(set(value)) != len(value):
            raise ValueError(f"methods listed twice: {value}")
        return value


class SRDSMRecipe(StrictModel):
    """``pipeline: sr_dsm`` — HR pair (or synthetic scene) -> LR pair -> DSM
    upscale and SR -> DSM per model, compared with the HR-pair DSM."""

    pipeline: Literal["sr_dsm"]
    name: str = "sr_dsm"
    input: InputSpec
    sr: SRSpec = SRSpec()
    grid: GridSpec = GridSpec()
    match: MatchSpec = MatchSpec()
    cluster: ClusterSpec = ClusterSpec()
    output: OutputSpec = OutputSpec()

    @model_validator(mode="after")
    def _pair(self):
        inp = self.input
        if inp.images is not None and len(inp.images) != 2:
            raise ValueError(f"input.images: the sr_dsm workflow takes a pair (2 images), got {len(inp.images)}")
        if inp.rpcs is not None and any(r is not None for r in inp.rpcs):
            raise ValueError("input.rpcs: sr_dsm needs the cameras in the images (tags or sidecar): "
                             "the LR and SR images carry regenerated RPC tags")
        if self.output.geoid is not None:
            raise ValueError("output.geoid: sr_dsm compares ellipsoidal heights; geoid output is not supported")
        return self


# ------------------------------------------------------------ pure helpers
def lr_grid(grid: GroundGrid, scale: int) -> GroundGrid:
    """``grid`` coarsened ``scale`` times: same CRS and outer corner, cells
    ``scale`` times larger (the last row/column may overhang ``grid``).

    LR cell ``k`` covers fine cells ``[k s, (k + 1) s)``; its centre is at
    ``x0 + (k + 0.5) s r``. The chunk is ``grid.chunk / scale`` (even, >= 32).
    """
    chunk = max(32, (grid.chunk // scale) // 2 * 2)
    return GroundGrid(grid.crs, grid.x0, grid.y0, grid.resolution * scale,
                      math.ceil(grid.width / scale), math.ceil(grid.height / scale), chunk)


def _linear_weights(src: np.ndarray, dst: np.ndarray) -> "sparse.csr_matrix":
    """Sparse ``(len(dst), len(src))`` matrix of 1-D linear interpolation
    on a regular axis (ascending or descending), extrapolating linearly
    beyond the outer samples."""
    n = src.size
    if n == 1:
        return sparse.csr_matrix(np.ones((dst.size, 1)))
    f = (dst - src[0]) / ((src[-1] - src[0]) / (n - 1))
    i0 = np.clip(np.floor(f).astype(np.int64), 0, n - 2)
    w = f - i0
    rows = np.repeat(np.arange(dst.size), 2)
    cols = np.stack([i0, i0 + 1], axis=1).ravel()
    vals = np.stack([1.0 - w, w], axis=1).ravel()
    return sparse.csr_matrix((vals, (rows, cols)), shape=(dst.size, n))


def _upsample_block(src: np.ndarray, ay, ax, min_weight: float) -> np.ndarray:
    """Bilinear weights ``ay`` (rows) and ``ax`` (columns) applied to the
    source window ``src`` with :func:`upsample_dsm`'s hole rule (float32)."""
    src = np.asarray(src, np.float64)
    valid = np.isfinite(src)
    num = (ax @ (ay @ np.where(valid, src, 0.0)).T).T
    den = (ax @ (ay @ valid.astype(np.float64)).T).T
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den >= min_weight - 1e-9, num / den, np.nan).astype(np.float32)


def _support(weights, start: int, stop: int) -> tuple[int, int]:
    """Source index range ``[i0, i1)`` that rows ``start:stop`` of a
    :func:`_linear_weights` matrix read."""
    cols = weights[start:stop].indices
    return int(cols.min()), int(cols.max()) + 1


def upsample_dsm(height: xr.DataArray, grid: GroundGrid, min_weight: float = 0.5) -> xr.DataArray:
    """Bilinear interpolation of a DSM at the cell centres of ``grid``.

    Parameters
    ----------
    height : xarray.DataArray
        DSM (metres), dims ``(y, x)`` with cell-centre coordinates, NaN =
        no height; e.g. on :func:`lr_grid` of ``grid``. Dask-backed or not.
    grid : GroundGrid
        Target grid (same CRS).
    min_weight : float
        A target cell gets a height when its valid source neighbours carry
        at least this fraction of its bilinear weight; the weights are then
        renormalised over them (GDAL's bilinear rule with nodata, plus a
        threshold). With the default 0.5 and a factor-2 grid, a target cell
        is valid when its nearest source cell is (weight 9/16), so holes
        keep their size instead of growing by a cell.

    Returns
    -------
    xarray.DataArray
        float32 heights on ``grid`` (CRS and transform written), lazy in
        ``grid.chunk`` blocks, each reading only the source cells under it
        (the same values as the whole grid at once). Target centres beyond
        the outer source centres (half a source cell at the edges) are
        extrapolated linearly.
    """
    import dask
    import dask.array as da
    import rioxarray  # noqa: F401  (registers .rio)

    src = height.data if isinstance(height.data, da.Array) else da.from_array(np.asarray(height.values))
    ay = _linear_weights(np.asarray(height.y.values, np.float64), grid.y)
    ax = _linear_weights(np.asarray(height.x.values, np.float64), grid.x)
    rows, cols = grid.chunks
    r_edges, c_edges = np.cumsum((0,) + tuple(rows)), np.cumsum((0,) + tuple(cols))
    blocks = []
    for r0, r1 in zip(r_edges[:-1], r_edges[1:]):
        i0, i1 = _support(ay, r0, r1)
        line = []
        for c0, c1 in zip(c_edges[:-1], c_edges[1:]):
            j0, j1 = _support(ax, c0, c1)
            block = dask.delayed(_upsample_block)(src[i0:i1, j0:j1], ay[r0:r1, i0:i1], ax[c0:c1, j0:j1], min_weight)
            line.append(da.from_delayed(block, (int(r1 - r0), int(c1 - c0)), dtype=np.float32))
        blocks.append(line)
    out = xr.DataArray(da.block(blocks), dims=("y", "x"), coords={"y": grid.y, "x": grid.x}, name=height.name)
    out.attrs = {k: v for k, v in height.attrs.items() if k in ("units", "long_name")}
    return out.rio.write_crs(grid.crs).rio.write_transform(grid.transform)


# ----------------------------------------------------------------- stages
def _dsm_recipe(recipe: SRDSMRecipe, views, grid: GroundGrid | None, folder: Path):
    """The ``pipeline: dsm`` recipe of one DSM of the run: on ``grid``, else
    on the recipe's grid (the HR DSM's default one)."""
    from tiledsm.workflows.stage_dsm import dsm_recipe, grid_spec

    spec = recipe.grid if grid is None else grid_spec(grid, chunk=max(32, grid.chunk // 2 * 2))
    return dsm_recipe(f"{recipe.name}-{folder.name}", views, None, spec, recipe.match, recipe.output, recipe.cluster)


def _make_dsm(views, grid, recipe, folder: Path, cluster: ClusterConfig, overwrite: bool, *,
              plan_cluster=None, limits=None) -> tuple[xr.DataArray, dict, GroundGrid]:
    """DSM of ``views`` on ``grid`` into ``folder`` by the DSM stage
    (:mod:`tiledsm.workflows.stage_dsm`: planned, memory-fitted, resumable);
    returns the stored height, a report and the grid it lies on."""
    from tiledsm.io import open_product
    from tiledsm.plan.core import Limits
    from tiledsm.workflows.stage_dsm import plan_stage_dsm, run_stage_dsm, stage_report

    t0 = time.perf_counter()
    sub = _dsm_recipe(recipe, views, grid, folder)
    plan = plan_stage_dsm(sub, folder, plan_cluster, overwrite=overwrite, limits=limits or Limits())
    metrics = run_stage_dsm(plan, sub, folder, cluster, overwrite=overwrite)
    report = stage_report(metrics)
    report["timings"] = {**(report["timings"] or {}), "total_s": time.perf_counter() - t0}
    return open_product(folder / "dsm.zarr")["height"], report, plan.prepared.grid


def _open_band(path: Path, chunk: int):
    """Band 1 of a raster as a dask array (float64, nodata -> NaN)."""
    import rioxarray

    arr = rioxarray.open_rasterio(path, chunks={"band": 1, "y": chunk, "x": chunk}, masked=True)
    return arr.isel(band=0).data.astype(np.float64)


def _super_resolve_file(lr: Path, out: Path, model: str, sr: SRSpec, cluster: ClusterConfig) -> Path:
    """Super-resolve one LR image into ``out`` (float32 DN, scaled RPC tags)."""
    from tiledsm.io import open_scene, scene_rpc, write_geotiff_with_rpc
    from tiledsm.sr.infer import super_resolve
    from tiledsm.sr.registry import load_pretrained

    net = load_pretrained(model, sr.scale, device=sr.device)
    kw = {"blur_sigma": sr.srmd_blur_sigma, "noise": sr.srmd_noise} if net.takes_degradation else {}
    scene = open_scene(lr, chunks=sr.chunk)
    scene.attrs["bit_depth"] = sr.bit_depth
    hr = super_resolve(scene, net, sr.scale, device=sr.device, normalisation=sr.normalisation, **kw)
    tags = {k: v for k, v in hr.attrs.items() if k.startswith("sr_")}
    tags["sr_model"] = model
    with compute_context(cluster):
        write_geotiff_with_rpc(hr, out, scene_rpc(hr), nodata=float("nan"), dtype="float32", tags=tags)
    return out


def _hr_pair(recipe: SRDSMRecipe, out: Path) -> tuple[list[Path], dict]:
    """The HR views and what is known about them (truth, reference)."""
    inp = recipe.input
    if inp.synth is not None:
        from tiledsm.synth import make_scene

        sy = inp.synth
        log.info("making synthetic scene %s", sy.model_dump())
        scene = make_scene(out / "scene", size=sy.size, gsd=sy.gsd, bh=sy.bh, seed=sy.seed, views=sy.views, event=False)
        info = {"truth": Path(scene.truth_dsm), "visible": Path(scene.visible_mask), "label": Path(scene.truth_label),
                "description": f"synthetic scene (size {sy.size} px, GSD {sy.gsd} m, B/H {sy.bh}, seed {sy.seed})"}
        return [Path(v) for v in scene.views[:2]], info
    views = [Path(p) for p in inp.images]
    for v in views:
        if not v.exists():
            raise SRDSMError(f"{v}: input.images: no such file")
    info = {"description": "HR pair " + ", ".join(v.name for v in views)}
    if inp.reference:
        info["reference"] = Path(inp.reference)
        if not info["reference"].exists():
            raise SRDSMError(f"{inp.reference}: input.reference: no such file")
    return views, info


def _target_grid(recipe: SRDSMRecipe, info: dict) -> GroundGrid | None:
    from tiledsm.recipes import grid_from_spec

    g = recipe.grid
    known = info.get("reference") or info.get("truth")
    if known is not None and not g.like:
        return grid_like(str(known), chunk=g.chunk)
    return grid_from_spec(g)


# ----------------------------------------------------------------- runner
def run_sr_dsm(recipe: SRDSMRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False,
               plan=None) -> dict:
    """Run ``pipeline: sr_dsm`` into ``out`` (see the module docstring).

    Each DSM is made by the DSM stage into its folder
    (:mod:`tiledsm.workflows.stage_dsm`); image quality is reduced block by
    block: no grid-sized array comes to this process. The run scores no DSM:
    ``tiledsm evaluate OUT`` (:mod:`tiledsm.evaluate.sr_dsm`) writes the DSM
    tables against the HR-pair DSM and the truth.

    Returns the metrics written to ``out/metrics.json``: per method, the
    image quality (``image``: PSNR dB, SSIM, per view and mean) and its
    DSM's report (``dsm``), the HR-pair DSM's report, timings in seconds.
    """
    from tiledsm.io import write_cog
    from tiledsm.plan.core import Limits
    from tiledsm.synth.degrade import degrade
    from tiledsm.workflows.common import DSM_DEFLATE_LEVEL, write_json
    from tiledsm.workflows.sr_scores import image_quality_lazy

    out = Path(out)
    plan_cluster = cluster = cluster or recipe.cluster.config()
    limits = plan.limits if plan is not None else Limits()
    sr = recipe.sr
    s = sr.scale
    border = s if sr.border is None else sr.border
    peak = float(2**sr.bit_depth - 1)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    views, info = _hr_pair(recipe, out)
    metrics: dict = {
        "pipeline": "sr_dsm", "name": recipe.name, "input": info["description"],
        "sr": {**sr.model_dump(), "border": border},
    }
    if info.get("reference"):
        metrics["reference"] = str(info["reference"])
    with shared_cluster(cluster) as run_cluster:
        def make_dsm(views, grid, folder):
            return _make_dsm(views, grid, recipe, folder, run_cluster, overwrite, plan_cluster=plan_cluster,
                             limits=limits)

        # 1. reference DSM from the HR pair, on G
        grid = _target_grid(recipe, info)
        log.info("sr_dsm: DSM of the HR pair")
        t0 = time.perf_counter()
        _, hr_report, grid = make_dsm(views, grid, out / "hr")
        timings["hr"] = time.perf_counter() - t0
        metrics["grid"] = {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height}
        metrics["hr"] = {"dsm": hr_report}
        # 2. LR pair
        t0 = time.perf_counter()
        lr_views = []
        for i, v in enumerate(views):
            target = out / "lr" / f"view_{i}.tif"
            target.parent.mkdir(parents=True, exist_ok=True)
            lr_views.append(degrade(v, target, scale=s, method=sr.degrade, sigma=sr.degrade_sigma,
                                    noise=sr.lr_noise, seed=i, bits=sr.bit_depth))
        timings["lr"] = time.perf_counter() - t0
        # 3. methods
        methods: dict[str, dict] = {}
        for name in sr.models:
            t0 = time.perf_counter()
            folder = out / name
            folder.mkdir(parents=True, exist_ok=True)
            log.info("sr_dsm: method %s", name)
            if name == UPSCALE:
                lr_height, report, _ = make_dsm(lr_views, lr_grid(grid, s), out / "lr")
                with compute_context(run_cluster):
                    write_cog(upsample_dsm(lr_height, grid), folder / "dsm.tif", level=DSM_DEFLATE_LEVEL)
                row: dict = {"dsm": {**report, "lr_grid_resolution": grid.resolution * s}}
            else:
                sr_views = [_super_resolve_file(lv, folder / f"sr_view_{i}.tif", name, sr, run_cluster)
                            for i, lv in enumerate(lr_views)]
                with compute_context(run_cluster):
                    per_view = [image_quality_lazy(_open_band(h, sr.chunk * s), _open_band(p, sr.chunk * s),
                                                   peak=peak, border=border) for h, p in zip(views, sr_views)]
                row = {"image": {
                    "psnr_db": float(np.mean([q["psnr_db"] for q in per_view])),
                    "ssim": float(np.mean([q["ssim"] for q in per_view])),
                    "views": per_view,
                }}
                _, row["dsm"], _ = make_dsm(sr_views, grid, folder)
            methods[name] = row
            timings[name] = time.perf_counter() - t0
    # the DSM tables (against the HR-pair DSM and the truth) are tiledsm evaluate's (tiledsm.evaluate.sr_dsm)
    metrics["methods"] = methods
    timings["total"] = time.perf_counter() - t_start
    metrics["timings"] = timings
    write_json(metrics, out / "metrics.json")
    from tiledsm.io import atomic_path

    with atomic_path(out / "report.md") as tmp:
        Path(tmp).write_text(markdown_report(metrics))
    log.info("sr_dsm: wrote %s", out / "report.md")
    return metrics


# ----------------------------------------------------------------- plan
def plan_sr_dsm(plan, recipe: SRDSMRecipe, cluster=None, *, overwrite: bool = False, names=None):
    """Fill ``plan`` (:func:`tiledsm.pipelines.plan_recipe`) for an ``sr_dsm``
    recipe: input files and SR weights, then every DSM the run makes, each
    with its grid, chunks, levels and worker memory (:attr:`Plan.stages`):
    ``hr`` (the DSM stage's plan of the HR pair; from the scene's
    parameters for a synthetic one, not made yet), ``lr`` (the LR pair's,
    for ``dsm_upscale``) and one per SR method, whose images the run makes
    first (:func:`tiledsm.workflows.stage_dsm.plan_unmade_dsm`: the cameras
    they will carry, the HR pair's heights)."""
    import dataclasses

    from tiledsm.dsm.views import View
    from tiledsm.plan.recipes import check_recipe_inputs
    from tiledsm.workflows.stage_dsm import (
        SYNTH_ITEMSIZE, add_stages, plan_stage_dsm, plan_unmade_dsm, scene_heights, synthetic_views,
    )

    check_recipe_inputs(plan, recipe)
    out, inp, s = plan.out, recipe.input, recipe.sr.scale
    if inp.synth is not None:
        from tiledsm.synth.layout import scene_layout

        sy = inp.synth
        lay = scene_layout(sy.size, sy.gsd, sy.bh, sy.seed, sy.views, False)
        grid = grid_like(recipe.grid.like, chunk=recipe.grid.chunk) if recipe.grid.like else \
            dataclasses.replace(lay.grid, chunk=recipe.grid.chunk)
        paths = [out / "scene" / f"view_{i}.tif" for i in range(2)]
        hr_views = synthetic_views(lay, lay.cameras[:2], paths)
        h_range = scene_heights(lay, recipe.match)
        hr_plan, grid = plan_unmade_dsm(out / "hr", hr_views, h_range, _dsm_recipe(recipe, paths, grid, out / "hr"),
                                        itemsize=SYNTH_ITEMSIZE, limits=plan.limits)
        plan.notes.append(f"synthetic scene {sy.size}² px at {sy.gsd:g} m is made by the run in {out / 'scene'}: its "
                          "DSMs are planned from its parameters (truth grid, fitted cameras, terrain heights); their "
                          "heights come from the scene's tie points once it is made")
    else:
        _, info = _hr_pair(recipe, out)
        hr_recipe = _dsm_recipe(recipe, inp.images, _target_grid(recipe, info), out / "hr")
        hr_plan = plan_stage_dsm(hr_recipe, out / "hr", cluster, overwrite=overwrite, limits=plan.limits)
        hr_views, h_range, grid = hr_plan.prepared.views, hr_plan.prepared.h_range, hr_plan.prepared.grid
    stages = [("hr", hr_plan)]
    if UPSCALE in recipe.sr.models:
        lr_views = [View(str(out / "lr" / f"view_{i}.tif"), v.rpc.scaled(1 / s), (v.shape[0] // s, v.shape[1] // s))
                    for i, v in enumerate(hr_views)]
        lr = lr_grid(grid, s)
        stages.append(("lr", plan_unmade_dsm(out / "lr", lr_views, h_range, _dsm_recipe(recipe, [v.path for v in lr_views], lr, out / "lr"),
                                             itemsize=SYNTH_ITEMSIZE, limits=plan.limits)[0]))
    for name in recipe.sr.models:
        if name == UPSCALE:
            continue
        sr_views = [View(str(out / name / f"sr_view_{i}.tif"), v.rpc, (v.shape[0] // s * s, v.shape[1] // s * s))
                    for i, v in enumerate(hr_views)]
        sub = _dsm_recipe(recipe, [v.path for v in sr_views], grid, out / name)
        stages.append((name, plan_unmade_dsm(out / name, sr_views, h_range, sub, itemsize=SR_ITEMSIZE,
                                             limits=plan.limits)[0]))
    return add_stages(plan, stages, "per DSM (above)")


#: bytes per pixel of the SR images (float32 DN, :func:`_super_resolve_file`)
SR_ITEMSIZE = 4
