"""Scores of a displacement field against a known truth: the ``displace``
pipeline's ``displacement.zarr`` and the ``displacement/`` of a
``deformation`` run.

The truth is either a synthetic event scene (the ``scene/`` folder a
deformation run makes, or ``tiledsm synth --event``: its ``scene.json``
names ``dx.tif``, ``dy.tif``, ``dz.tif`` and the event's parameters) or a
folder holding the true ``dE.tif``, ``dN.tif`` (and ``dU.tif``): metres
east/north/up, post minus pre, on any grid and CRS.

On the field grid (one cell every ``step`` ortho pixels), the truth of a
cell is its mean over the cell's ``step`` x ``step`` ortho pixels, each
read at its centre (nearest cell of the truth raster), chunk by chunk:
only the field-sized result is held, never the truth rasters.

Frame: the run removed a plane (or the median) fitted on stable terrain
from each component (:mod:`tiledsm.displace.correct`), so the truth is
compared in the same frame -- minus its median over the stable cells --
unless the run corrected nothing (a ``displace`` run without a stable
mask: the grids' own frame). Cells whose correlation window straddles the
fault trace mix both blocks and are left out of the per-cell errors.

Scores (:func:`score_fields`): per component the error statistics on all,
stable and moving cells and the share within +-2 sigma; with a fault, the
truth of each measured offset across it and its error, and the truth's
profiles; with an event's uplift, the mean ``dU`` error where the uplift
exceeds half its peak.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tiledsm.errors import InputFileError, NoOverlapError

__all__ = ["COMPONENTS", "DisplacementTruth", "FieldGrid", "open_truth", "scene_truth", "truth_on_field",
           "score_fields", "score", "write_truth_cogs", "write_error_quicklooks", "write_profiles_with_truth"]

#: the components a displacement field may hold
COMPONENTS = ("dE", "dN", "dU")
#: the event rasters of a synthetic scene holding each component's truth
EVENT_RASTERS = {"dE": "dx", "dN": "dy", "dU": "dz"}


@dataclass(frozen=True)
class DisplacementTruth:
    """A known displacement: ``rasters`` maps a component (``dE``, ``dN``,
    ``dU``) to the raster of its truth (metres, post minus pre); ``event``
    (:class:`tiledsm.synth.event.EventParams`) and ``origin`` (easting,
    northing of the scene's local origin, metres) where it is a synthetic
    event."""

    source: Path
    rasters: dict
    event: object | None = None
    origin: tuple | None = None


@dataclass(frozen=True)
class FieldGrid:
    """The grid of a displacement field: ``x``, ``y`` cell centres (metres,
    ``crs``), ``transform`` (GDAL, top-left corner), ``step`` ortho pixels
    per cell side."""

    transform: object
    crs: object
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    step: int

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.y), len(self.x)

    @property
    def ortho_res(self) -> float:
        """Metres per ortho pixel."""
        return abs(float(self.transform.a)) / self.step


def scene_truth(scene) -> DisplacementTruth:
    """The truth of a synthetic scene made with an event
    (:class:`tiledsm.synth.SceneInfo`, or one reopened by
    :func:`tiledsm.evaluate.scenes.open_scene`)."""
    ev = scene.event
    return DisplacementTruth(Path(scene.out_dir), {n: Path(ev[k]) for n, k in EVENT_RASTERS.items()},
                             ev["params"], tuple(scene.origin))


def open_truth(path: str | Path, name: str = "--truth") -> DisplacementTruth:
    """The truth in ``path``: a synthetic event scene (folder or its
    ``scene.json``) or a folder of true ``dE.tif``, ``dN.tif`` (``dU.tif``).

    Raises
    ------
    InputFileError
        Missing, or neither kind of truth (``name``: how the user gave it).
    """
    from tiledsm.evaluate.scenes import is_scene, open_scene

    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{path}: {name}: no such file or folder")
    folder = path.parent if path.name == "scene.json" else path
    if is_scene(folder):
        return scene_truth(open_scene(folder, name, event=True))
    rasters = {n: folder / f"{n}.tif" for n in COMPONENTS if (folder / f"{n}.tif").is_file()}
    if not folder.is_dir() or not {"dE", "dN"} <= set(rasters):
        raise InputFileError(f"{path}: {name}: neither a synthetic event scene (scene.json) nor a folder with "
                             "the true dE.tif and dN.tif")
    return DisplacementTruth(folder, rasters)


def _cell_means(raster: Path, grid: FieldGrid, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """Mean of ``raster`` over each field cell of the window, read at the
    centres of its step x step ortho pixels (nearest truth cell; NaN
    outside the raster)."""
    import rasterio
    from affine import Affine
    from rasterio.enums import Resampling
    from rasterio.vrt import WarpedVRT
    from rasterio.windows import Window

    s = grid.step
    t = grid.transform
    fine = Affine(t.a / s, 0, t.c, 0, t.e / s, t.f)
    (r0, r1), (c0, c1) = rows, cols
    with rasterio.open(raster) as src, WarpedVRT(src, crs=grid.crs, transform=fine, width=grid.shape[1] * s,
                                                 height=grid.shape[0] * s, resampling=Resampling.nearest,
                                                 src_nodata=src.nodata, nodata=np.nan, dtype="float32") as vrt:
        a = vrt.read(1, window=Window(c0 * s, r0 * s, (c1 - c0) * s, (r1 - r0) * s), masked=True)
    a = np.ma.filled(a.astype(np.float64), np.nan)
    return a.reshape(r1 - r0, s, c1 - c0, s).mean(axis=(1, 3))


def truth_on_field(raster: str | Path, grid: FieldGrid, chunk: int = 256) -> np.ndarray:
    """The truth of ``raster`` on the field grid (module notes), computed
    chunk by chunk (``chunk`` field cells per side), float64."""
    import dask
    import dask.array as da

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"]
        return _cell_means(Path(raster), grid, (r0, r1), (c0, c1))

    chunks = da.core.normalize_chunks(chunk, grid.shape)
    lazy = da.map_blocks(block, chunks=chunks, dtype=np.float64, meta=np.empty((0, 0), np.float64))
    (out,) = dask.compute(lazy)
    return out


def _uplift_share(event, origin, x, y) -> np.ndarray:
    """The uplift's shape (0..1) on the field cells (local metres: minus the scene origin)."""
    xx = np.asarray(x)[None, :] - origin[0] - event.uplift_center[0]
    yy = np.asarray(y)[:, None] - origin[1] - event.uplift_center[1]
    g = np.exp(-0.5 * (xx**2 + yy**2) / event.uplift_sigma**2)
    if event.still == "left":
        nx_, ny_ = event.normal
        side = ((np.asarray(x)[None, :] - origin[0] - event.fault_point[0]) * nx_
                + (np.asarray(y)[:, None] - origin[1] - event.fault_point[1]) * ny_) >= 0
        g = np.where(side, g, 0.0)
    return g


def _offsets_truth(truth: dict, fields: dict, fault, distance, fault_doc: dict, event) -> dict:
    """The truth of each offset the run measured across the fault (the same
    strips and cells) and the error of the measurement."""
    from tiledsm.workflows.fault import throw_across

    strip = tuple(fault_doc["strip_m"])
    s, nrm = fault.strike, fault.normal
    tcomp = {"along_strike": truth["dE"] * s[0] + truth["dN"] * s[1],
             "across_strike": truth["dE"] * nrm[0] + truth["dN"] * nrm[1]}
    if "dU" in truth:
        tcomp["dU"] = truth["dU"]
    off = {}
    for name, t in tcomp.items():
        meas = fault_doc["offsets"].get(name)
        if meas is None:
            continue
        valid = np.isfinite(fields["dE"]) & np.isfinite(fields["dU"] if name == "dU" else fields["dE"])
        tt = throw_across(t, distance, strip, valid)["throw"]
        off[name] = {"measured": meas["offset"], "truth": tt, "error": meas["offset"] - tt,
                     "stated_error": meas["error"]}
    if event is not None:
        off["nominal"] = {"slip": float(event.slip), "throw": float(event.throw)}
    edges = np.asarray(fault_doc["profiles"]["distance_m"])
    bw = edges[1] - edges[0] if edges.size > 1 else 1.0
    k = np.digitize(distance, np.concatenate([edges - bw / 2, [edges[-1] + bw / 2]])) - 1
    profiles = {"truth_" + name: [float(np.median(t[k == b])) if (k == b).any() else float("nan")
                                  for b in range(edges.size)] for name, t in tcomp.items()}
    return {"offsets": off, "profiles": profiles}


def score_fields(fields: dict, sigmas: dict, stable: np.ndarray, grid: FieldGrid, truth: DisplacementTruth, *,
                 window: int, corrected: bool = True, fault=None, fault_doc: dict | None = None,
                 chunk: int = 256) -> tuple[dict, dict]:
    """Errors of a displacement field against ``truth`` (module notes).

    Parameters
    ----------
    fields, sigmas : dict of ndarray
        ``dE``, ``dN`` (and ``dU``) and their standard errors on ``grid``,
        metres, NaN where unknown.
    stable : ndarray of bool
        The stable terrain the run's frame was fitted on.
    window : int
        Correlation window side, ortho pixels.
    corrected : bool
        Whether the run removed a stable-terrain frame (else the truth is
        compared as is).
    fault : tiledsm.workflows.fault.Fault, optional
        The trace; ``fault_doc``: the run's fault section (strips, measured
        offsets, profiles), for the offsets' truth.

    Returns
    -------
    doc : dict
        ``frame`` (the truth's shift into the stable frame, metres),
        ``components`` (per component: ``all``, ``stable``, ``moving``
        error statistics, ``within_2_sigma``; ``all.nmad_px``), and where
        they apply ``offsets``, ``profiles``, ``uplift``.
    truth : dict of ndarray
        The truth on the field grid, in the compared frame.

    Raises
    ------
    NoOverlapError
        The truth covers no cell of the field.
    """
    from tiledsm.displace.uncertainty import coverage
    from tiledsm.workflows.fault import error_stats

    names = [n for n in COMPONENTS if n in fields and n in truth.rasters]
    on_field = {n: truth_on_field(truth.rasters[n], grid, chunk) for n in names}
    if not any(np.isfinite(on_field[n]).any() for n in names):
        raise NoOverlapError(f"{truth.source}: --truth: covers no cell of the run's displacement field")
    frame = {n: (float(np.median(on_field[n][stable & np.isfinite(on_field[n])])) if corrected else 0.0)
             for n in names}
    truth_f = {n: on_field[n] - frame[n] for n in names}
    res = grid.ortho_res
    distance = None if fault is None else fault.signed_distance(grid.x, grid.y)
    near = (np.zeros(grid.shape, bool) if distance is None
            else np.abs(distance) < 0.5 * window * res + grid.step * res)
    doc: dict = {"frame": {n: -frame[n] for n in names}, "components": {}}
    for n in names:
        err = fields[n] - truth_f[n]
        ok = np.isfinite(err) & ~near
        doc["components"][n] = {
            "all": error_stats(err[ok]), "stable": error_stats(err[ok & stable]),
            "moving": error_stats(err[ok & ~stable]), "within_2_sigma": coverage(err[ok], sigmas[n][ok]),
        }
        doc["components"][n]["all"]["nmad_px"] = doc["components"][n]["all"].get("nmad", np.nan) / res
    if distance is not None and fault_doc is not None and {"dE", "dN"} <= set(names):
        doc.update(_offsets_truth(truth_f, fields, fault, distance, fault_doc, truth.event))
    if truth.event is not None and truth.event.uplift and "dU" in names:
        # the uplift where it exceeds half its peak, away from the fault: mean dU error there
        up = _uplift_share(truth.event, truth.origin, grid.x, grid.y)
        sel = (up > 0.5) & np.isfinite(fields["dU"]) & ~near
        if sel.any():
            doc["uplift"] = {"cells": int(sel.sum()), "measured_mean": float(np.mean(fields["dU"][sel])),
                             "truth_mean": float(np.mean(truth_f["dU"][sel])),
                             "error": float(np.mean(fields["dU"][sel] - truth_f["dU"][sel]))}
    return doc, truth_f


def _on_grid(a: np.ndarray, grid: FieldGrid):
    import rioxarray  # noqa: F401  (registers .rio)
    import xarray as xr

    arr = xr.DataArray(a.astype(np.float32), dims=("y", "x"), coords={"y": grid.y, "x": grid.x})
    return arr.rio.write_crs(grid.crs).rio.write_transform(grid.transform)


def write_truth_cogs(truth: dict, grid: FieldGrid, folder: Path, prefix: str = "true_") -> list[Path]:
    """The truth on the field grid as COGs ``<prefix><component>.tif``."""
    from tiledsm.io import write_cog

    written = []
    for n, a in truth.items():
        write_cog(_on_grid(a, grid), folder / f"{prefix}{n}.tif")
        written.append(folder / f"{prefix}{n}.tif")
    return written


def write_error_quicklooks(fields: dict, truth: dict, grid: FieldGrid, folder: Path) -> list[Path]:
    """``error_<component>.png``: the field minus its truth, metres (symmetric
    colour limits, magenta where the run measured nothing)."""
    from tiledsm.quicklook import quicklook

    return [quicklook(_on_grid(fields[n] - t, grid), folder / f"error_{n}.png", kind="difference",
                      title=f"{n} - truth (m)") for n, t in truth.items()]


def write_profiles_with_truth(fault_doc: dict, truth_profiles: dict, folder: Path) -> Path:
    """``profiles.png``: the run's profiles across the fault (its fault
    section: ``profiles``, ``offsets``) with the truth's (``truth_<name>``)."""
    from tiledsm.displace.figures import profile_figure

    return profile_figure({**fault_doc["profiles"], **truth_profiles}, fault_doc["offsets"], folder / "profiles.png",
                          title="across the fault trace, with the truth")


def _stable_mask_of(run_dir: Path, recipe: dict) -> str | None:
    """The stable-mask polygons the run's frame was fitted on (a deformation
    run on a synthetic event writes its own into ``scene/``)."""
    if recipe["pipeline"] == "displace":
        return recipe.get("stable_mask")
    given = (recipe.get("compare") or {}).get("stable_mask")
    auto = run_dir / "scene" / "stable_mask.geojson"
    return given or (str(auto) if auto.is_file() else None)


def _fault_of(metrics: dict, section: dict, truth: DisplacementTruth):
    """The trace the run measured its offsets across (its metrics, else the event's)."""
    from tiledsm.workflows.fault import Fault

    for doc in (section.get("fault") or {}, metrics.get("fault") or {}):
        if "point" in doc and "strike" in doc:
            return Fault(doc["point"], doc["strike"])
    if truth.event is not None:
        return Fault(np.asarray(truth.event.fault_point) + np.asarray(truth.origin), truth.event.strike)
    return None


def score(run_dir: Path, truth: str | Path | None = None) -> dict:
    """Score the displacement field of a finished ``displace`` or
    ``deformation`` run folder against ``truth`` (module notes; default:
    the synthetic scene the run made, ``scene/``).

    Returns the :func:`score_fields` document with ``truth`` (where it came
    from) and ``products`` (the field scored); writes the truth on the
    field grid as ``true_dE.tif`` ... and the error maps ``error_dE.png`` ...
    into ``evaluation/`` and, with the run's offsets across a fault,
    ``profiles.png`` (its profiles with the truth's).

    Raises
    ------
    InputFileError
        No displacement field in the run, no truth given or found, or a
        truth of neither kind.
    NoOverlapError
        The truth covers no cell of the field.
    """
    import yaml

    from tiledsm.compare.stable import exclusion_mask, read_polygons
    from tiledsm.io import open_product

    run_dir = Path(run_dir)
    recipe = yaml.safe_load((run_dir / "recipe.resolved.yaml").read_text())
    pipeline = recipe["pipeline"]
    products = run_dir / "displacement" if pipeline == "deformation" else run_dir
    store = products / "displacement.zarr"
    if not store.exists():
        raise InputFileError(f"{run_dir}: no displacement field ({store.relative_to(run_dir)}): nothing to score "
                             f"(a {pipeline} run without a displacement, or one that did not finish)")
    if truth is None:
        if not (run_dir / "scene" / "scene.json").is_file():
            raise InputFileError(f"{run_dir}: the run made no synthetic scene: give --truth (a synthetic event "
                                 "scene, or a folder with the true dE.tif, dN.tif)")
        truth = run_dir / "scene"
    known = open_truth(truth)
    metrics = json.loads((run_dir / "metrics.json").read_text()) if (run_dir / "metrics.json").is_file() else {}
    section = metrics.get("displacement", {}) if pipeline == "deformation" else metrics
    spec = recipe["displacement"]
    ds = open_product(store)
    fields = {n: np.asarray(ds[n].values, np.float64) for n in COMPONENTS if n in ds}
    sigmas = {n: np.asarray(ds[f"sigma_{n}"].values, np.float64) for n in fields}
    grid = FieldGrid(ds.rio.transform(), ds.rio.crs, ds.x.values, ds.y.values, int(spec["step"]))
    mask = _stable_mask_of(run_dir, recipe)
    stable = np.ones(grid.shape, bool)
    if mask:
        stable = ~exclusion_mask(read_polygons(mask, grid.crs), grid.transform, grid.shape)
    doc, truth_f = score_fields(fields, sigmas, stable, grid, known, window=int(spec["window"]),
                                corrected=pipeline == "deformation" or bool(mask),
                                fault=_fault_of(metrics, section, known), fault_doc=section.get("fault"))
    (run_dir / "evaluation").mkdir(exist_ok=True)
    written = [*write_truth_cogs(truth_f, grid, run_dir / "evaluation"),
               *write_error_quicklooks(fields, truth_f, grid, run_dir / "evaluation")]
    fault_doc = section.get("fault")
    if fault_doc is not None and "profiles" in doc:
        written.append(write_profiles_with_truth(fault_doc, doc["profiles"], run_dir / "evaluation"))
    return {"truth": str(known.source), "field": str(store.relative_to(run_dir)),
            "stable_mask": mask, **doc, "products": [str(p.relative_to(run_dir)) for p in written]}
