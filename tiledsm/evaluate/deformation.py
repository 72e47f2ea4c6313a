"""Scores of a finished deformation run against a truth, chunk by chunk.

:func:`score` (the ``deformation`` scorer of :data:`tiledsm.evaluate.SCORERS`,
``tiledsm evaluate RUN_DIR``) rebuilds the truth of a run folder of
``pipeline: deformation`` from the folder alone (:func:`truth_of`): the
synthetic event scene the run made (``scene/``), with the stable mask the
run fitted its co-registration on (``compare.stable_mask`` of its
``recipe.resolved.yaml``, else the ``scene/stable_mask.geojson`` it wrote)
and the event's fault; for real inputs the recipe's ``input.truth_dh`` and
``input.truth_mask`` and ``fault.trace``; or ``--truth`` (a synthetic event
scene or a ``dh`` raster). It scores ``compare/dh.zarr`` (:func:`score_dh`)
and, when the run has one, the ``displacement/`` field
(:func:`tiledsm.evaluate.displacement.score`).

Every grid-sized quantity (truth ``dh`` on the run's grid, masks, errors)
stays a dask array: statistics are histogram reductions
(:class:`tiledsm.compare.stats.HistogramStats`, medians to a bin of
``range / 2**18``), the throw reads only the cells of its strips
(:func:`tiledsm.workflows.fault.strips_lazy`).

Conventions: metres; ``dh = post - pre``; the frame of the synthetic truth
is the one of :mod:`tiledsm.workflows.deformation` (module notes): the
co-registration expected from the truth displacement over the stable cells
is applied to the post-event truth before it is differenced.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import dask
import dask.array as da
import numpy as np
import xarray as xr

from tiledsm.compare.stats import HistogramStats
from tiledsm.errors import InputFileError, TiledsmError
from tiledsm.workflows.fault import Fault, strips_lazy, throw_of_strips

__all__ = ["DeformationTruth", "truth_of", "score", "score_dh", "error_stats_lazy"]

#: histogram bins of the medians, NMAD and 95th percentile
BINS = 2**18


@dataclass(frozen=True)
class DeformationTruth:
    """What a deformation run is scored against.

    Attributes
    ----------
    scene : SceneInfo, SyntheticScene or None
        The synthetic event scene (:func:`tiledsm.synth.make_scene` with
        ``event=True``, or reopened by :func:`tiledsm.evaluate.scenes.open_scene`)
        whose truth rasters are read.
    dh, mask : str or None
        Without a scene: a truth ``dh`` raster (metres, ``post - pre``) and
        optionally a uint8 raster, 1 where it is evaluated.
    stable_mask : str or None
        GeoJSON of the areas the run excluded from stable terrain (the
        expected co-registration is fitted on the other cells).
    fault : Fault or None
        Trace across which the throw is scored; ``strip`` its strips (m).
    """

    scene: object | None = None
    dh: str | None = None
    mask: str | None = None
    stable_mask: str | None = None
    fault: Fault | None = None
    strip: tuple[float, float] = (3.0, 20.0)


# --------------------------------------------------------------------------- lazy statistics
def _partial(err, keep, hs: HistogramStats):
    sel = keep & np.isfinite(err)
    return hs.block_packed(np.where(sel, err, np.nan), np.ones_like(err), sel[None], sel[None])


def _fold_quantile(hs: HistogramStats, hist: np.ndarray, q: float) -> float:
    """q-quantile of ``|value|`` from a histogram of the values (bin centres)."""
    w = (hs.hi - hs.lo) / hs.bins
    dev = np.abs(hs.lo + (np.arange(hs.bins) + 0.5) * w)
    order = np.argsort(dev, kind="stable")
    cum = np.cumsum(hist[1:-1][order])
    k = int(np.searchsorted(cum, q * hist.sum(), side="left"))
    return float(dev[order][k]) if k < dev.size else float("nan")


def error_stats_lazy(err: da.Array, keep: da.Array | None = None) -> dict:
    """:func:`tiledsm.workflows.fault.error_stats` of the finite cells of a
    dask array where ``keep`` holds, by two reductions (range, then
    histogram and moments): count, rmse, mean (exact), median, nmad, le95
    (to a histogram bin)."""
    keep = da.isfinite(err) if keep is None else keep & da.isfinite(err)
    sel = da.where(keep, err, np.nan)
    lo, hi = dask.compute(da.nanmin(sel), da.nanmax(sel))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return {"count": 0}
    pad = max(1e-6, 1e-6 * (hi - lo))
    hs = HistogramStats(("all",), float(lo) - pad, float(hi) + pad, BINS)
    total = hs.unpack(hs.lazy_total(partial(_partial, hs=hs), err, keep).compute())
    stats = hs.finalize(total, with_mre=False)["all"]
    return {"count": stats["count"], "rmse": stats["rmse"], "mean": stats["mean"], "median": stats["median"],
            "nmad": stats["nmad"], "le95": _fold_quantile(hs, total["hist"][0], 0.95)}


def lazy_median(values: da.Array, keep: da.Array) -> tuple[float, int]:
    """Median (to a histogram bin) and count of the finite ``values`` where ``keep``."""
    stats = error_stats_lazy(values, keep)
    return stats.get("median", float("nan")), stats["count"]


# --------------------------------------------------------------------------- truth on the run's grid
def _on_grid(path, like: xr.DataArray, nearest: bool = False) -> da.Array:
    """A raster on the grid and chunks of ``like`` (dask, float32, NaN = none)."""
    from tiledsm.compare.align import align_dsms, open_dsm

    chunk = int(like.data.chunks[0][0])
    other = align_dsms(like, open_dsm(path, chunk), chunks=chunk,
                       resampling="nearest" if nearest else "bilinear").other.data
    return other.rechunk(like.data.chunks)


def _shifted(a: da.Array, dy: float, dx: float, kernel: str) -> da.Array:
    """:func:`tiledsm.compare.coreg.shift_array` chunk by chunk (with its
    halo: bit for bit the whole array's)."""
    from tiledsm.compare.coreg import shift_array, shift_halo

    depth = shift_halo(dy, dx, kernel)
    return da.map_overlap(shift_array, a, depth=depth, boundary="none", dtype=np.float32,
                          dy=dy, dx=dx, kernel=kernel)


def expected_coregistration_lazy(scene, dh: xr.DataArray, stable_mask: str | None) -> dict:
    """:func:`tiledsm.workflows.fault.expected_coregistration` on the run's
    grid, lazily (medians of the truth displacement over the stable cells)."""
    from tiledsm.compare.stable import exclusion_mask_lazy, read_polygons

    ev = scene.event
    transform = dh.rio.transform()
    geoms = read_polygons(stable_mask, dh.rio.crs) if stable_mask else []
    stable = ~exclusion_mask_lazy(geoms, transform, dh.data) & da.isfinite(dh.data)
    res = float(transform.a)
    (mx, n), (my, _), (mz, _) = (lazy_median(_on_grid(ev[k], dh), stable) for k in ("dx", "dy", "dz"))
    if n == 0:
        return {"dx_px": 0.0, "dy_px": 0.0, "dz": 0.0, "n_cells": 0}
    return {"dx_px": -mx / res, "dy_px": my / res, "dz": -mz, "n_cells": int(n)}


def synthetic_truth(scene, dh: xr.DataArray, expected: dict):
    """Lazy ``(truth_dh, visible, visible_ground)`` on the grid of ``dh``
    in the frame of ``expected`` (module notes of the deformation workflow)."""
    ev = scene.event
    dy_px, dx_px, dz = expected["dy_px"], expected["dx_px"], expected["dz"]
    pre = _on_grid(scene.truth_dsm, dh)
    post = _on_grid(ev["post_dsm"], dh)
    vis = _on_grid(scene.visible_mask, dh, nearest=True) > 0.5
    pvis = _on_grid(ev["post_visible"], dh, nearest=True)
    lab = _on_grid(scene.truth_label, dh, nearest=True)
    plab = _on_grid(ev["post_label"], dh, nearest=True)
    if dx_px or dy_px:
        post = _shifted(post, dy_px, dx_px, "cubic")
        # masks: linear weights; a cell counts only when all its support does
        pvis = _shifted(pvis, dy_px, dx_px, "linear")
        pground = _shifted((plab == 0).astype(np.float32), dy_px, dx_px, "linear") > 0.999
    else:
        pground = plab == 0
    truth = post.astype(np.float64) + dz - pre.astype(np.float64)
    visible = vis & (da.nan_to_num(pvis) > 0.999) & da.isfinite(truth)
    return truth, visible, visible & (lab == 0) & pground


# --------------------------------------------------------------------------- scores
def _throw(dh: xr.DataArray, truth: da.Array, fault: Fault, strip, valid: da.Array) -> dict:
    measured = throw_of_strips(*strips_lazy(dh, fault, strip, valid), strip)
    true = throw_of_strips(*strips_lazy(dh.copy(data=truth), fault, strip, valid), strip)
    return {"measured": measured, "truth": true}


def score_dh(run_dir: Path, truth: DeformationTruth) -> dict:
    """Errors of a deformation run's ``dh`` (``compare/dh.zarr``) against ``truth``.

    Synthetic scene: ``frame``, ``coregistration_expected``,
    ``coregistration_error`` (found minus expected), ``dh_error_visible_ground``,
    ``dh_error_visible`` (:func:`error_stats_lazy` of ``dh - truth``),
    ``completeness_visible_ground`` and, with a fault, ``throw``
    (``recovered``, ``truth``, ``error``, ``nominal``, ``cells``). Truth
    raster: ``source``, ``dh_error`` and, with a fault, ``throw``.
    """
    from tiledsm.io import open_product

    run_dir = Path(run_dir)
    dh = open_product(run_dir / "compare" / "dh.zarr")["dh"]
    if truth.scene is None:
        true = _on_grid(truth.dh, dh).astype(np.float64)
        sel = da.isfinite(true) & da.isfinite(dh.data)
        if truth.mask:
            sel &= _on_grid(truth.mask, dh, nearest=True) > 0.5
        out: dict = {"source": str(truth.dh), "dh_error": error_stats_lazy(dh.data - true, sel)}
        if truth.fault is not None:
            t = _throw(dh, true, truth.fault, truth.strip, sel)
            out["throw"] = {"recovered": t["measured"]["throw"], "truth": t["truth"]["throw"],
                            "error": t["measured"]["throw"] - t["truth"]["throw"]}
        return out
    coreg = json.loads((run_dir / "compare" / "metrics.json").read_text())["coregistration"]
    ev = truth.scene.event
    if coreg["method"] == "none":
        expected = {"dx_px": 0.0, "dy_px": 0.0, "dz": 0.0, "n_cells": 0}
    else:
        expected = expected_coregistration_lazy(truth.scene, dh, truth.stable_mask)
    true, visible, ground = synthetic_truth(truth.scene, dh, expected)
    ok = da.isfinite(dh.data)
    err = dh.data - true
    n_ok_ground, n_ground = dask.compute((ok & ground).sum(), ground.sum())
    out = {
        "frame": "plain truth dh" if not (expected["dx_px"] or expected["dy_px"] or expected["dz"])
        else "truth dh in the frame of the stable terrain (expected co-registration applied to the post truth)",
        "coregistration_expected": expected,
        "coregistration_error": {
            "dx_px": coreg["dx_px"] - expected["dx_px"], "dy_px": coreg["dy_px"] - expected["dy_px"],
            "dz": coreg["dz"] - expected["dz"],
        },
        "dh_error_visible_ground": error_stats_lazy(err, ok & ground),
        "dh_error_visible": error_stats_lazy(err, ok & visible),
        "completeness_visible_ground": float(n_ok_ground / max(int(n_ground), 1)),
    }
    if truth.fault is not None:
        t = _throw(dh, true, truth.fault, truth.strip, ok & ground)
        mt, tt = t["measured"], t["truth"]
        out["throw"] = {"recovered": mt["throw"], "truth": tt["throw"], "error": mt["throw"] - tt["throw"],
                        "nominal": float(ev["params"].throw), "cells": [mt["n_left"], mt["n_right"]]}
    return out


# --------------------------------------------------------------------------- the truth of a run folder
def _event_fault(scene) -> Fault:
    """The trace of a synthetic event (as the run measured its throw across it)."""
    ev = scene.event["params"]
    return Fault(np.asarray(ev.fault_point) + np.asarray(scene.origin), ev.strike)


def _stable_mask_of(run_dir: Path, recipe) -> str | None:
    """The polygons the run fitted its co-registration outside of: the
    recipe's, else the ones it wrote from the known event."""
    auto = run_dir / "scene" / "stable_mask.geojson"
    return recipe.compare.stable_mask or (str(auto) if auto.is_file() else None)


def _fault_of(run_dir: Path, recipe, crs) -> Fault | None:
    """The trace of a run scored against a ``dh`` raster: the recipe's
    ``fault.trace``, else the event of the scene the run made."""
    from tiledsm.evaluate.scenes import is_scene, open_scene
    from tiledsm.workflows.deformation import fault_from_trace

    if recipe.fault is not None:
        return fault_from_trace(recipe.fault, crs)
    if is_scene(run_dir / "scene"):
        return _event_fault(open_scene(run_dir / "scene", "RUN_DIR/scene", event=True))
    return None


def truth_of(run_dir: Path, recipe, truth: str | Path | None, crs) -> DeformationTruth:
    """The :class:`DeformationTruth` of a finished run folder (module notes).

    Parameters
    ----------
    recipe : DeformationRecipe
        The run's resolved recipe.
    truth : path or None
        ``--truth``: a synthetic event scene (folder or ``scene.json``) or a
        ``dh`` raster (metres, post - pre); default: the run's ``scene/``,
        else its ``input.truth_dh``.
    crs
        CRS of the run's ``dh`` grid (the recipe's fault trace is projected
        into it).

    Raises
    ------
    InputFileError
        No truth given and none in the run, a truth that does not exist, or
        a folder that is no synthetic event scene.
    """
    from tiledsm.evaluate.scenes import is_scene, open_scene

    strip = tuple(recipe.compare.strip)
    name = "--truth" if truth is not None else "RUN_DIR/scene"
    if truth is None:
        if is_scene(run_dir / "scene"):
            truth = run_dir / "scene"
        elif recipe.input.truth_dh:
            return DeformationTruth(dh=recipe.input.truth_dh, mask=recipe.input.truth_mask,
                                    fault=_fault_of(run_dir, recipe, crs), strip=strip)
        else:
            raise InputFileError(f"{run_dir}: the run made no synthetic scene (scene/) and its recipe has no "
                                 "input.truth_dh: give --truth (a synthetic event scene or a dh raster)")
    truth = Path(truth)
    if not truth.exists():
        raise InputFileError(f"{truth}: --truth: no such file or folder")
    if is_scene(truth):
        scene = open_scene(truth, name, event=True)
        return DeformationTruth(scene=scene, stable_mask=_stable_mask_of(run_dir, recipe), fault=_event_fault(scene),
                                strip=strip)
    if truth.is_dir():
        raise InputFileError(f"{truth}: --truth: neither a synthetic event scene (scene.json) nor a dh raster")
    return DeformationTruth(dh=str(truth), fault=_fault_of(run_dir, recipe, crs), strip=strip)


def score(run_dir: Path, truth: str | Path | None = None) -> dict:
    """Score a finished ``deformation`` run folder (module notes).

    Returns
    -------
    dict
        ``truth`` (where it came from), ``stable_mask``, ``dh``
        (:func:`score_dh`) and, for a run with a ``displacement/`` field and
        a synthetic event truth, ``displacement``
        (:func:`tiledsm.evaluate.displacement.score`) and its ``products``.

    Raises
    ------
    InputFileError
        The run did not finish (no ``compare/dh.zarr``), or no truth
        (:func:`truth_of`).
    NoOverlapError, GridError
        A truth that covers none of the run's grid (the message names
        ``--truth``).
    """
    from tiledsm.evaluate import resolved_recipe
    from tiledsm.io import open_product
    from tiledsm.workflows.deformation import DeformationRecipe

    run_dir = Path(run_dir)
    recipe = resolved_recipe(run_dir, DeformationRecipe)
    store = run_dir / "compare" / "dh.zarr"
    if not store.exists():
        raise InputFileError(f"{run_dir}: no compare/dh.zarr: the deformation run did not finish (nothing to score)")
    known = truth_of(run_dir, recipe, truth, open_product(store)["dh"].rio.crs.to_string())
    source = known.scene.out_dir if known.scene is not None else known.dh
    doc: dict = {"truth": str(source), "stable_mask": known.stable_mask}
    try:
        doc["dh"] = score_dh(run_dir, known)
    except TiledsmError as exc:  # a given truth that does not fit this run: say it is the truth's fault
        if truth is None:
            raise
        raise type(exc)(f"--truth: {exc}") from None
    if (run_dir / "displacement" / "displacement.zarr").exists():
        if known.scene is None:
            doc["displacement"] = {"not_scored": f"{source}: a dh raster holds no true dE, dN: give a synthetic "
                                                 "event scene as --truth to score the displacement"}
        else:
            from tiledsm.evaluate.displacement import score as score_displacement

            doc["displacement"] = score_displacement(run_dir, known.scene.out_dir)
            doc["products"] = doc["displacement"].pop("products")
    return doc
