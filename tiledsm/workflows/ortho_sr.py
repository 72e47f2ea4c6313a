"""Multi-image super-resolution of UAV orthoimages: the ``ortho_sr`` workflow.

The experiment of the UAV multi-image SR paper (SR-S, SR-R, SR-O; issue
11) on a synthetic UAV block with truth (:mod:`tiledsm.synth.uav`) or on a
block of the user's files (``input.block``), plus the project's
single-image CNNs on one LR ortho, in one table.

Steps (``pipeline: ortho_sr``), all under the run folder:

1. the block (:func:`load_block`): frames, nominal cameras, true HR ortho
   and DSM (:func:`tiledsm.synth.uav.make_uav_scene`, written to
   ``scene/``), or the files of ``input.block``
   (:func:`tiledsm.ortho.block.read_block`; scored only when it names a
   reference ortho, ``truth``);
2. for each DSM of ``misr.dsm_noise`` (metres of Gaussian noise added to
   every HR cell of the true DSM; 0 = the true DSM) and each radius of
   ``misr.radii`` (focal-plane millimetres, :func:`radial_select`; None =
   all images), the methods (:func:`run_method`):

   - ``SR-S`` with each kernel of ``misr.sr_s`` (one image, no radius);
   - ``SR-R`` with each kernel of ``misr.sr_r``;
   - ``SR-O`` with each kernel of ``misr.sr_o`` x each PSF of ``misr.psfs``
     (``square``, ``gauss1``, ``gauss2``, ``gauss3``: Gaussian sigma in HR
     cells), at most ``misr.max_iter`` iterations or ``E(t) <= misr.te``;
   - each CNN of ``misr.cnn`` (:mod:`tiledsm.sr` registry, shipped weights)
     on the reference image's ortho on the LR grid (``scale`` x the HR
     cell), super-resolved ``scale`` times (:func:`cnn_ortho`);

3. per row: ``products/<slug>.zarr``, ``.tif`` (COG), ``.png``, ``.json``
   (:func:`tiledsm.ortho.stage.write_ortho_products`, atomic);
4. ``report.md`` and, last, ``metrics.json`` with ``rows``: ``method``,
   ``kernel``, ``psf``, ``images``, ``scale``, ``radius_mm``,
   ``dsm_noise_m``, ``psnr``, ``ssim``, ``resolved_px`` (narrowest stripe
   group with Michelson contrast >= 0.1, HR cells;
   :func:`tiledsm.misr.metrics.resolved_px`), ``shift_px``, ``psnr_raw``,
   ``ssim_raw`` (:func:`score`), ``iterations`` (SR-O), ``product``; a
   method whose registration left fewer than 2 images is listed under
   ``skipped`` with the reason instead.

Conventions
-----------
- HR grid = LR GSD / ``scale``; the truth and every product are on it
  (corner convention: LR ortho cell ``k`` covers HR cells ``[k s, (k+1) s)``).
- PSNR/SSIM peak 255 DN, ``2 scale`` cells cropped on each side, over the
  cells finite in both the truth and the product, after the products'
  common georeferencing shift is removed (:func:`score`; ``psnr_raw``,
  ``ssim_raw`` without).
- Heights are the synthetic block's (ellipsoidal, metres).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import xarray as xr
from pydantic import Field, field_validator, model_validator

from tiledsm.cluster import ClusterConfig, compute_context
from tiledsm.errors import TiledsmError
from tiledsm.geometry.grid import GroundGrid
from tiledsm.recipes import ClusterSpec, OutputSpec, StrictModel

log = logging.getLogger("tiledsm")

__all__ = [
    "KERNELS",
    "PSFS",
    "OrthoSRError",
    "UAVSynthSpec",
    "MISRSpec",
    "OrthoSRRecipe",
    "Row",
    "psf_from_label",
    "noisy_dsm",
    "lr_ortho",
    "cnn_ortho",
    "align_to",
    "score",
    "record",
    "run_method",
    "markdown_report",
    "run_ortho_sr",
]

KERNELS = ("nn", "bl", "cr", "cs")
PSFS = ("square", "gauss1", "gauss2", "gauss3")
_PSF_LABEL = Literal["square", "gauss1", "gauss2", "gauss3"]
_KERNEL = Literal["nn", "bl", "cr", "cs"]


class OrthoSRError(TiledsmError):
    """Raised when a step of the ortho_sr workflow cannot run (the message
    names the recipe field)."""


# ------------------------------------------------------------------ schema
class UAVSynthSpec(StrictModel):
    """The synthetic UAV block (fields of :class:`tiledsm.synth.uav.UAVParams`;
    its ``scale`` is ``misr.scale``)."""

    frames: int = Field(16, ge=16, le=40, description="frames of the serpentine flight")
    rows: int = Field(100, ge=32, description="frame rows, pixels")
    cols: int = Field(130, ge=32, description="frame columns, pixels")
    roi: int = Field(160, ge=160, description="ROI side, HR cells (the chart needs 160)")
    lr_gsd: float = Field(0.02, gt=0, description="frame GSD at nadir, metres")
    altitude: float = Field(30.0, gt=0, description="flying height, metres")
    noise: float = Field(1.0, ge=0, description="sensor noise, DN (std)")
    blur_centre: float = Field(0.35, ge=0, description="lens blur sigma at the principal point, LR px")
    blur_edge: float = Field(1.1, ge=0, description="lens blur sigma at the frame corner, LR px")
    supersample: int = Field(2, ge=1, le=4, description="rays per pixel side")
    seed: int = 0


class MISRSpec(StrictModel):
    """Methods and options of ``pipeline: ortho_sr`` (module docstring)."""

    scale: int = Field(2, ge=2, le=4, description="LR GSD / HR cell")
    sr_s: list[_KERNEL] = Field(default_factory=lambda: ["cr", "cs"], description="SR-S kernels")
    sr_r: list[_KERNEL] = Field(default_factory=lambda: ["cs"], description="SR-R kernels")
    sr_o: list[_KERNEL] = Field(default_factory=lambda: ["cs"], description="SR-O kernels (orthos and registration)")
    psfs: list[_PSF_LABEL] = Field(default_factory=lambda: ["square"], description="SR-O PSFs")
    radii: list[Optional[float]] = Field(default_factory=lambda: [None], min_length=1,
                                         description="radial selection, focal-plane mm (null: all images)")
    dsm_noise: list[float] = Field(default_factory=lambda: [0.0], min_length=1,
                                   description="DSM noise std, metres (0: the true DSM)")
    dsm_noise_seed: int = 0
    cnn: list[str] = Field(default_factory=list, description="single-image SR networks on one LR ortho")
    cnn_kernel: _KERNEL = Field("cs", description="kernel of the LR ortho the CNNs start from")
    srmd_blur_sigma: float = Field(1.0, ge=0, description="SRMD's blur sigma, HR px")
    max_iter: int = Field(10, ge=1, description="SR-O iterations at most")
    te: float = Field(0.0, ge=0, description="SR-O stops when E(t) <= te (DN^2)")
    chunk: int = Field(64, ge=16, description="HR tile side of the orthos and IBP")
    occlusion: bool = Field(True, description="orthos leave cells hidden by the DSM NaN (a noisy DSM hides many)")

    @field_validator("cnn")
    @classmethod
    def _known_cnn(cls, value: list[str]) -> list[str]:
        from tiledsm.sr.registry import MODELS

        bad = [m for m in value if m not in MODELS.names()]
        if bad:
            raise ValueError(f"unknown SR network(s) {bad}; known: {MODELS.names()}")
        return value

    @field_validator("dsm_noise")
    @classmethod
    def _non_negative(cls, value: list[float]) -> list[float]:
        if any(not v >= 0 for v in value):
            raise ValueError(f"DSM noise must be >= 0 metres, got {value}")
        return value


class BlockSpec(StrictModel):
    """A real block from files (:func:`tiledsm.ortho.block.read_block`)."""

    images: list[str] = Field(..., min_length=1, description="the frames (band 1, DN)")
    cameras: str = Field(..., description="YAML block file with every image's frame camera")
    dsm: str = Field(..., description="heights in the cameras' CRS and datum, covering the region")
    bounds: tuple[float, float, float, float] = Field(..., description="region: left bottom right top, cameras' CRS")
    resolution: float = Field(..., gt=0, description="HR cell, metres (LR GSD / misr.scale)")
    truth: Optional[str] = Field(None, description="reference ortho on the region (scores); none: products only")


class OrthoSRInput(StrictModel):
    """Input block: the synthetic UAV scene (default) or a real block of
    files (``block``), not both."""

    synth: Optional[UAVSynthSpec] = None
    block: Optional[BlockSpec] = None

    @model_validator(mode="before")
    @classmethod
    def _one_source(cls, data):
        if isinstance(data, dict):
            if data.get("synth") is not None and data.get("block") is not None:
                raise ValueError("give either 'synth' (a synthetic block) or 'block' (files), not both")
            if data.get("block") is None and data.get("synth") is None:
                data = {**data, "synth": {}}
        return data


class OrthoSRRecipe(StrictModel):
    """``pipeline: ortho_sr`` — a UAV block -> SR-S / SR-R / SR-O (and CNN)
    orthos on the HR grid, scored against the true ortho."""

    pipeline: Literal["ortho_sr"]
    name: str = "ortho_sr"
    input: OrthoSRInput = OrthoSRInput()
    misr: MISRSpec = MISRSpec()
    cluster: ClusterSpec = ClusterSpec()
    output: OutputSpec = OutputSpec()

    @model_validator(mode="after")
    def _consistent(self):
        if self.output.geoid is not None:
            raise ValueError("output.geoid: ortho_sr writes images, not heights")
        if self.input.synth is not None and self.input.synth.roi % self.misr.scale:
            raise ValueError(f"input.synth.roi: must be a multiple of misr.scale {self.misr.scale}, "
                             f"got {self.input.synth.roi}")
        return self


# ------------------------------------------------------------ pure helpers
@dataclass(frozen=True)
class Row:
    """One method run (a row of ``metrics.json``)."""

    method: str
    kernel: str
    psf: Optional[str]
    radius_mm: Optional[float]
    dsm_noise_m: float

    @property
    def slug(self) -> str:
        parts = [self.method.lower().replace("-", ""), self.kernel, self.psf or "",
                 "all" if self.radius_mm is None else f"r{self.radius_mm:g}mm", f"dsm{self.dsm_noise_m:g}m"]
        return "_".join(p for p in parts if p)


def psf_from_label(label: str):
    """The :class:`~tiledsm.misr.ibp.PSF` of ``square`` or ``gaussS`` (sigma S HR cells)."""
    from tiledsm.misr.ibp import PSF

    if label == "square":
        return PSF("square")
    if label.startswith("gauss"):
        return PSF("gaussian", float(label[5:]))
    raise OrthoSRError(f"misr.psfs: expected one of {list(PSFS)}, got {label!r}")


def noisy_dsm(dsm: np.ndarray, std: float, seed: int = 0) -> np.ndarray:
    """``dsm`` plus white Gaussian noise of ``std`` metres per cell (``dsm`` itself when 0)."""
    if std == 0:
        return dsm
    rng = np.random.default_rng(seed)
    return (dsm + rng.normal(0.0, std, dsm.shape)).astype(dsm.dtype)


def lr_ortho(inputs, index: int, kernel: str) -> np.ndarray:
    """Ortho of image ``index`` on the LR grid (``scale`` HR cells per cell,
    same outer corner), on the HR DSM's block mean."""
    from tiledsm.misr.methods import SRInputs, ortho_hr

    g, s = inputs.grid, inputs.scale
    lr = GroundGrid(g.crs, g.x0, g.y0, g.resolution * s, g.width // s, g.height // s, max(16, g.chunk // s))
    d = np.asarray(inputs.dsm, np.float64)[: lr.height * s, : lr.width * s]
    d = d.reshape(lr.height, s, lr.width, s).mean(axis=(1, 3))
    return ortho_hr(SRInputs(inputs.frames, inputs.cameras, lr, d, 1, inputs.occlusion), index, kernel)


def cnn_ortho(lr: np.ndarray, model: str, scale: int, *, srmd_blur_sigma: float = 1.0) -> np.ndarray:
    """``lr`` (DN 0..255) super-resolved ``scale`` times by a shipped network
    (:func:`tiledsm.sr.infer.sr_array`; NaN filled with the mean first and
    put back on the covered cells). Without native weights for ``scale``
    the x2 network runs repeatedly (:func:`tiledsm.sr.registry.weight_chain`;
    SRMD with the same degradation map at each pass)."""
    from tiledsm.sr.infer import resolve_model, sr_array
    from tiledsm.sr.registry import weight_chain

    chain = weight_chain(model, scale)
    if chain is None:
        raise OrthoSRError(f"misr.cnn: no weights for {model!r} at x{scale} (nor x2 weights to apply twice)")
    nan = ~np.isfinite(lr)
    img = np.where(nan, np.nanmean(lr), lr)
    kw = {"blur_sigma": srmd_blur_sigma, "noise": 0.0} if model == "srmd" else {}
    for s in chain:
        img = sr_array(img, resolve_model(model, s), value_scale=255.0, **kw)
    img[np.repeat(np.repeat(nan, scale, axis=0), scale, axis=1)] = np.nan
    return img


def cnn_scheme(model: str, scale: int) -> str | None:
    """How a CNN row reaches ``scale``: ``"x2 applied twice"`` (or more)
    when it has no native weights, ``None`` when it has."""
    from tiledsm.sr.registry import chain_scheme, weight_chain

    chain = weight_chain(model, scale)
    return None if chain is None else chain_scheme(chain)


def align_to(truth: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """``image`` shifted onto ``truth``: the translation ``(ty, tx)`` (HR
    cells, :mod:`tiledsm.misr.register` convention: the image's content at
    ``q + t`` is the truth's at ``q``) by ECC, removed by a cubic-spline
    shift; cells shifted in from outside or from NaN are NaN. Returns the
    image unchanged and NaN shifts when ECC fails."""
    from scipy import ndimage

    from tiledsm.misr.register import register

    reg = register(image, truth)
    if not np.isfinite(reg.ecc):
        return image, (float("nan"), float("nan"))
    nan = ~np.isfinite(image)
    f = np.where(nan, np.nanmean(image), image)
    out = ndimage.shift(f, (-reg.ty, -reg.tx), order=3, mode="nearest")
    out[ndimage.shift(nan.astype(float), (-reg.ty, -reg.tx), order=1, mode="constant", cval=1.0) > 0] = np.nan
    return out, (reg.ty, reg.tx)


def score(truth: np.ndarray, image: np.ndarray, chart, scale: int) -> dict:
    """Image quality against the true ortho (peak 255, ``2 scale`` cells cropped).

    Every product shares the georeferencing error of the reference image's
    nominal camera (a sub-cell shift no method can see without ground
    control), which PSNR would charge more to sharper images. So ``psnr``,
    ``ssim`` and ``resolved_px`` are measured after that shift is removed
    (:func:`align_to`, reported as ``shift_px`` = ``[ty, tx]``);
    ``psnr_raw``/``ssim_raw`` are on the product as written. ``valid`` is
    the share of the scored cells that have a value (NaN cells, e.g.
    hidden by the DSM, are left out of every score).
    """
    from tiledsm.misr.metrics import resolved_px
    from tiledsm.sr.metrics import psnr, ssim

    b = 2 * scale
    aligned, shift = align_to(truth, image)
    return {"valid": float(np.isfinite(aligned[b:-b, b:-b]).mean()),
            "psnr": psnr(truth, aligned, data_range=255, border=b),
            "ssim": ssim(truth, aligned, data_range=255, border=b),
            "resolved_px": resolved_px(aligned, chart), "shift_px": [round(shift[0], 4), round(shift[1], 4)],
            "psnr_raw": psnr(truth, image, data_range=255, border=b),
            "ssim_raw": ssim(truth, image, data_range=255, border=b)}


def record(row: Row, rep: dict, scores: dict, scale: int) -> dict:
    """A row of ``metrics.json`` (module docstring)."""
    out = {"method": row.method, "kernel": row.kernel, "psf": row.psf, "images": int(rep["images"]), "scale": scale,
           "radius_mm": row.radius_mm, "dsm_noise_m": row.dsm_noise_m, **scores,
           "iterations": rep.get("iterations"), "reference": int(rep["reference"])}
    if rep.get("scheme"):
        out["scheme"] = rep["scheme"]
    if row.method in ("SR-R", "SR-O") and out["images"] < 2:
        out["warning"] = f"ECC registered {out['images']} image(s) to the reference: no multi-image SR happened"
    return out


def run_method(inputs, row: Row, misr: MISRSpec) -> tuple[np.ndarray, dict]:
    """Image and report of one row (``inputs`` a :class:`SRInputs`; the
    radius selects the images of SR-R/SR-O)."""
    from tiledsm.misr.methods import radial_select, reference_index, sr_o, sr_r, sr_s

    if row.method == "SR-S":
        return sr_s(inputs, row.kernel)
    if row.method in ("SR-R", "SR-O"):
        idx = radial_select(inputs, row.radius_mm)
        if row.method == "SR-R":
            return sr_r(inputs, row.kernel, idx)
        return sr_o(inputs, psf_from_label(row.psf), row.kernel, idx, max_iter=misr.max_iter, te=misr.te)
    ref = reference_index(inputs)
    lr = lr_ortho(inputs, ref, row.kernel)
    rep = {"reference": ref, "images": 1, "scheme": cnn_scheme(row.method, inputs.scale)}
    return cnn_ortho(lr, row.method, inputs.scale, srmd_blur_sigma=misr.srmd_blur_sigma), rep


def planned_rows(misr: MISRSpec) -> list[Row]:
    """Every row of a recipe, in table order."""
    rows = []
    for noise in misr.dsm_noise:
        rows += [Row("SR-S", k, None, None, noise) for k in misr.sr_s]
        for r in misr.radii:
            rows += [Row("SR-R", k, None, r, noise) for k in misr.sr_r]
            rows += [Row("SR-O", k, p, r, noise) for k in misr.sr_o for p in misr.psfs]
        rows += [Row(m, misr.cnn_kernel, None, None, noise) for m in misr.cnn]
    return rows


def _fmt(v, spec: str) -> str:
    return "–" if v is None or not np.isfinite(v) else format(v, spec)


def markdown_report(metrics: dict) -> str:
    """``report.md``: one line per row, the method's table shape."""
    lines = [
        f"# Multi-image SR of orthoimages: {metrics['name']}",
        "",
        f"{'Synthetic UAV' if metrics['input']['synth'] else 'UAV'} block ({metrics['input']['frames']} frames), "
        f"HR grid {metrics['grid']['resolution']:g} m "
        f"(LR GSD / {metrics['scale']}), {metrics['grid']['width']} x {metrics['grid']['height']} cells. "
        + (f"PSNR/SSIM against the true ortho (peak 255, {2 * metrics['scale']} cells cropped); "
           + ("resolved: narrowest stripe group (HR cells) with Michelson contrast >= 0.1; " if metrics["input"]["synth"]
              else "")
           + "scores after removing the products' common georeferencing shift (the reference camera's pose error; "
           "`shift_px`, `psnr_raw` in metrics.json)."
           if metrics["truth"] is not None else "No reference ortho given: products only, not scored."),
        "",
        "| Method | Kernel | PSF | Images | Radius (mm) | DSM noise (m) | PSNR (dB) | SSIM | Resolved (px) | Valid (%) "
        "| Iter. |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in metrics["rows"]:
        rad = "all" if r["radius_mm"] is None else f"{r['radius_mm']:g}"
        method = f"{r['method']} ({r['scheme']})" if r.get("scheme") else r["method"]
        lines.append(f"| {method} | {r['kernel'].upper()} | {r['psf'] or '–'} | {r['images']} | {rad} | "
                     f"{r['dsm_noise_m']:g} | {_fmt(r['psnr'], '.2f')} | {_fmt(r['ssim'], '.4f')} | "
                     f"{r['resolved_px'] if r['resolved_px'] is not None else '–'} | {100 * r['valid']:.1f} | "
                     f"{r.get('iterations') or '–'} |")
    for s in metrics.get("skipped", []):
        lines.append(f"\nSkipped {s['method']}: {s['why']}")
    lines += ["", f"Total time {metrics['timings']['total_s']:.1f} s.", ""]
    return "\n".join(lines)


def _as_array(img: np.ndarray, grid: GroundGrid, attrs: dict) -> xr.DataArray:
    import rioxarray  # noqa: F401

    a = xr.DataArray(np.asarray(img, np.float32), dims=("y", "x"), coords=grid.coords(), name="ortho", attrs=attrs)
    return a.rio.write_crs(grid.crs).rio.write_transform(grid.transform).chunk(grid.chunk)


@dataclass(frozen=True)
class LoadedBlock:
    """What the runner works on: frames, cameras, the HR grid (chunks of
    ``misr.chunk``), the DSM and truth on it (truth None: not scored), the
    stripe chart (empty for real blocks) and ``about`` (for metrics.json)."""

    frames: list
    cameras: list
    grid: GroundGrid
    dsm: np.ndarray
    truth: Optional[np.ndarray]
    chart: list
    about: dict


def load_block(recipe: OrthoSRRecipe, out: Path) -> LoadedBlock:
    """The synthetic block (written to ``out/scene``) or the files of
    ``input.block``."""
    m, sy, bl = recipe.misr, recipe.input.synth, recipe.input.block
    if bl is not None:
        from tiledsm.ortho.block import read_block

        b = read_block(bl.images, bl.cameras, bl.dsm, bl.bounds, bl.resolution, chunk=m.chunk, truth=bl.truth,
                       multiple=m.scale)
        about = {"synth": False, "frames": len(b.frames), "images": b.names, "cameras": bl.cameras, "dsm": bl.dsm,
                 "truth": bl.truth}
        return LoadedBlock(b.frames, b.cameras, b.grid, b.dsm, b.truth, [], about)
    from tiledsm.synth.uav import UAVParams, make_uav_scene

    params = UAVParams(scale=m.scale, **sy.model_dump())
    log.info("making the synthetic UAV block %s", params)
    scene = make_uav_scene(params, out / "scene")
    g = scene.grid
    grid = GroundGrid(g.crs, g.x0, g.y0, g.resolution, g.width, g.height, m.chunk)
    about = {"synth": True, "frames": len(scene.frames), "shape": [sy.rows, sy.cols]}
    return LoadedBlock(scene.frames, scene.cameras, grid, scene.dsm, scene.truth, scene.chart, about)


def unscored(image: np.ndarray, scale: int) -> dict:
    """The scores of a product without a truth: only ``valid`` (share of
    finite cells, ``2 scale`` cells cropped)."""
    b = 2 * scale
    return {"valid": float(np.isfinite(image[b:-b, b:-b]).mean()), "psnr": None, "ssim": None,
            "resolved_px": None, "shift_px": None, "psnr_raw": None, "ssim_raw": None}


# ----------------------------------------------------------------- runner
def run_ortho_sr(recipe: OrthoSRRecipe, out: Path, cluster: ClusterConfig | None = None,
                 overwrite: bool = False) -> dict:
    """Run ``pipeline: ortho_sr`` into ``out`` (module docstring); returns
    the metrics written to ``out/metrics.json`` (last)."""
    from tiledsm.misr.methods import MISRError, RegistrationError, SRInputs
    from tiledsm.misr.metrics import resolved_px
    from tiledsm.ortho.stage import write_ortho_products
    from tiledsm.workflows.common import write_json
    from tiledsm.io import atomic_path
    from tiledsm.sr.registry import weight_chain

    t_start = time.perf_counter()
    cluster = cluster or recipe.cluster.config()
    m = recipe.misr
    scene = load_block(recipe, out)
    grid = scene.grid
    sync = ClusterConfig(scheduler="synchronous", progress=False)  # products are in memory
    inputs = {n: SRInputs(scene.frames, scene.cameras, grid, noisy_dsm(scene.dsm, n, m.dsm_noise_seed), m.scale,
                          occlusion=m.occlusion) for n in m.dsm_noise}
    rows, skipped, timings = [], [], {"scene_s": time.perf_counter() - t_start}
    products = out / "products"
    with compute_context(cluster):
        for row in planned_rows(m):
            if row.method not in ("SR-S", "SR-R", "SR-O") and weight_chain(row.method, m.scale) is None:
                if not any(s["method"] == row.method for s in skipped):
                    skipped.append({"method": row.method, "why": f"no weights at x{m.scale} (nor x2 to apply twice)"})
                continue
            t0 = time.perf_counter()
            try:
                img, rep = run_method(inputs[row.dsm_noise_m], row, m)
            except RegistrationError as exc:  # a data outcome, not a recipe error: reported, not scored
                skipped.append({"method": row.method, "slug": row.slug, "why": str(exc)})
                log.warning("%s skipped: %s", row.slug, exc)
                continue
            except MISRError as exc:
                raise OrthoSRError(f"misr ({row.slug}): {exc}") from None
            dt = time.perf_counter() - t0
            write_ortho_products(_as_array(img, grid, {"method": row.method, "kernel": row.kernel}), products,
                                 cluster=sync, cog=recipe.output.cog, quicklook=recipe.output.quicklook,
                                 name=row.slug)
            scores = unscored(img, m.scale) if scene.truth is None else score(scene.truth, img, scene.chart, m.scale)
            rows.append({**record(row, rep, scores, m.scale), "time_s": dt,
                         "product": str((products / f"{row.slug}.zarr").relative_to(out))})
            log.info("%s: %s", row.slug, rows[-1])
    truth = None
    if scene.truth is not None:
        write_ortho_products(_as_array(scene.truth, grid, {"method": "truth"}), products, cluster=sync,
                             cog=recipe.output.cog, quicklook=recipe.output.quicklook, name="truth")
        truth = {"resolved_px": resolved_px(scene.truth, scene.chart), "product": "products/truth.zarr"}
    timings["total_s"] = time.perf_counter() - t_start
    metrics = {
        "pipeline": "ortho_sr", "name": recipe.name, "scale": m.scale, "input": scene.about,
        "grid": {"crs": grid.crs, "resolution": grid.resolution, "width": grid.width, "height": grid.height,
                 "chunk": grid.chunk},
        "truth": truth, "rows": rows, "skipped": skipped, "timings": timings,
    }
    with atomic_path(out / "report.md") as tmp:
        Path(tmp).write_text(markdown_report(metrics))
    write_json(metrics, out / "metrics.json")
    return metrics
