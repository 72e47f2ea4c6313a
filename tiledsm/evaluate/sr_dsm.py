"""Scores of a finished ``sr_dsm`` run: the paper's DSM tables.

:func:`score` reads a run folder of ``pipeline: sr_dsm`` (``hr/dsm.zarr``,
``<method>/dsm.zarr`` or ``dsm_upscale/dsm.tif``) and an :class:`SRDSMTruth`
(the synthetic scene's truth, visibility and labels, or a reference DSM),
and returns the DSM tables of ``metrics.json``: every method against the
HR-pair DSM (``vs_hr``), the HR pair and every method against the truth on
visible cells (``vs_truth_visible``) or the reference (``vs_reference``),
each on its common cells (:func:`tiledsm.workflows.sr_scores.compare_on_common`),
and, with a synthetic truth, the four-region breakdown.

No grid-sized array is held: every DSM, truth and mask is read lazily
and decimated to at most :data:`MAX_TABLE_CELLS` cells (every ``step``-th
row and column, the same cells for every array; ``step`` is 1 up to
768² cells, so the shipped recipes are scored on every cell). Region
slopes are taken on the decimated truth (cells ``step`` times larger).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import xarray as xr

from tiledsm.workflows.sr_scores import RegionRule, compare_by_region, compare_on_common, regions_from_truth

__all__ = ["MAX_TABLE_CELLS", "SRDSMTruth", "table_step", "score", "score_tables", "write_blunder_map"]

#: the tables are scored on at most this many cells (a decimated grid beyond):
#: every cell of the shipped recipes' grids (512², s2p's 739 x 721), and this
#: process's share of the tables stays the same for any larger scene
MAX_TABLE_CELLS = 768 * 768


@dataclass(frozen=True)
class SRDSMTruth:
    """What an ``sr_dsm`` run is scored against beyond its HR-pair DSM.

    Attributes
    ----------
    truth, visible, label : str or None
        Synthetic truth heights (metres), visibility mask (uint8, 1 = seen
        by every view) and surface classes (0 ground, 1 building, 2 tree).
    reference : str or None
        A reference DSM (any grid; resampled bilinearly).
    """

    truth: str | None = None
    visible: str | None = None
    label: str | None = None
    reference: str | None = None


def table_step(shape: tuple[int, int], max_cells: int = MAX_TABLE_CELLS) -> int:
    """Row and column step that leaves at most ``max_cells`` cells of a grid."""
    return max(1, math.ceil(math.sqrt(shape[0] * shape[1] / max_cells)))


def method_dsm(run_dir: Path, name: str) -> Path:
    """Where a run keeps a method's DSM (the store, else the COG)."""
    store = Path(run_dir) / name / "dsm.zarr"
    return store if store.exists() else Path(run_dir) / name / "dsm.tif"


def _open(path: Path, chunk: int) -> xr.DataArray:
    from tiledsm.compare.align import open_dsm

    return open_dsm(path, chunk)


def _decimated(arr: xr.DataArray, step: int) -> np.ndarray:
    return np.asarray(arr.data[::step, ::step].compute() if hasattr(arr.data, "compute") else arr.values[::step, ::step],
                      np.float64)


def _on_grid(path: str, like: xr.DataArray, step: int, nearest: bool = False) -> np.ndarray:
    """A raster on the grid of ``like``, decimated (float64, NaN = none)."""
    from tiledsm.compare.align import align_dsms

    chunk = int(like.data.chunks[0][0])
    other = align_dsms(like, _open(Path(path), chunk), chunks=chunk,
                       resampling="nearest" if nearest else "bilinear").other
    return _decimated(other, step)


def load(run_dir: Path, methods: Sequence[str], truth: SRDSMTruth) -> dict:
    """The decimated heights (``hr`` and each method) and references of a run."""
    run_dir = Path(run_dir)
    hr = _open(run_dir / "hr" / "dsm.zarr", 512)
    step = table_step(hr.shape)
    heights = {"hr": _decimated(hr, step)}
    for name in methods:
        heights[name] = _decimated(_open(method_dsm(run_dir, name), 512), step)
    refs: dict = {}
    found: dict = {"step": step, "heights": heights, "refs": refs, "resolution": float(abs(hr.rio.transform().a)) * step}
    if truth.truth:
        t = _on_grid(truth.truth, hr, step)
        visible = _on_grid(truth.visible, hr, step, nearest=True) > 0.5
        refs["vs_truth_visible"] = (t, visible)
        found["label"] = _on_grid(truth.label, hr, step, nearest=True)
    if truth.reference:
        refs["vs_reference"] = (_on_grid(truth.reference, hr, step), None)
    return found


def score_tables(hr: np.ndarray, methods: dict[str, np.ndarray], refs: dict) -> tuple[dict, dict]:
    """Every table's statistics, each on its common cells.

    ``vs_hr`` compares ``methods`` against the HR-pair DSM ``hr``; each key
    of ``refs`` (``(reference, mask)``) compares the HR pair and ``methods``
    against that reference. Returns ``(scores, common)``: ``scores[name][key]``
    and ``common[key]`` (see :func:`compare_on_common`; heights in metres).
    """
    tables = {"vs_hr": compare_on_common(methods, hr)}
    for key, (ref, mask) in refs.items():
        tables[key] = compare_on_common({"hr": hr, **methods}, ref, mask)
    scores: dict[str, dict] = {}
    for key, table in tables.items():
        for name, row in table["scores"].items():
            scores.setdefault(name, {})[key] = row
    return scores, {key: table["common"] for key, table in tables.items()}


def score(run_dir: Path, truth: SRDSMTruth, methods: Sequence[str]) -> dict:
    """The DSM tables of an ``sr_dsm`` run (module notes).

    Returns
    -------
    dict
        ``scores`` (``scores[name][table]``, ``name`` in ``hr`` and
        ``methods``), ``common`` (each table's common cells), ``table_step``
        (the decimation) and, with a synthetic truth, ``regions``.
    """
    found = load(run_dir, methods, truth)
    heights, refs = found["heights"], found["refs"]
    scores, common = score_tables(heights["hr"], {k: v for k, v in heights.items() if k != "hr"}, refs)
    out = {"scores": scores, "common": common, "table_step": found["step"]}
    if "vs_truth_visible" in refs:
        rule = RegionRule()
        t, visible = refs["vs_truth_visible"]
        regions = regions_from_truth(t, found["label"], visible, found["resolution"], rule)
        out["regions"] = {
            "rule": f"flat ground: slope < {rule.flat_max_deg:g} deg, steep terrain: >= {rule.steep_min_deg:g} deg",
            "dsms": list(heights),
            "tables": compare_by_region(heights, t, regions),
        }
    return out


def write_blunder_map(run_dir: Path, truth: SRDSMTruth, methods: Sequence[str], path: Path) -> Path:
    """Blunder quick-look (decimated) against the best reference there is:
    the truth (visible ground), the given reference DSM, else the HR-pair DSM."""
    from tiledsm.workflows.sr_figures import blunder_map

    found = load(run_dir, methods, truth)
    heights, refs, res = found["heights"], found["refs"], found["resolution"]
    for key, title in (("vs_truth_visible", "against the truth, visible ground"),
                       ("vs_reference", "against the reference DSM")):
        if key in refs:
            ref, mask = refs[key]
            evaluated = np.ones(ref.shape, bool) if mask is None else mask
            return blunder_map(heights, ref, evaluated, res, path, title)
    hr = heights["hr"]
    return blunder_map({k: v for k, v in heights.items() if k != "hr"}, hr, np.ones(hr.shape, bool), res, path,
                       "against the HR-pair DSM")
