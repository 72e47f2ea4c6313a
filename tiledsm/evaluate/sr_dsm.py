"""Scores of a finished ``sr_dsm`` run: the paper's DSM tables.

:func:`score` (the ``sr_dsm`` scorer of :data:`tiledsm.evaluate.SCORERS`,
``tiledsm evaluate RUN_DIR``) reads a run folder of ``pipeline: sr_dsm``
(``hr/dsm.zarr``, ``<method>/dsm.zarr`` or ``dsm_upscale/dsm.tif``, the
methods of its ``recipe.resolved.yaml``) and its truth (:func:`truth_of`:
the synthetic scene it made, ``scene/``, else its ``input.reference``, or
``--truth``: a synthetic scene or a reference DSM) and returns the DSM
tables (:func:`dsm_tables`): every method against the HR-pair DSM
(``vs_hr``), the HR pair and every method against the truth on visible
cells (``vs_truth_visible``) or the reference (``vs_reference``), each on
its common cells (:func:`tiledsm.workflows.sr_scores.compare_on_common`),
and, with a synthetic truth, the four-region breakdown. It writes
``evaluation/report.md`` (the run's Table 1 of image quality and these
tables) and ``evaluation/blunders.png``.

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

from tiledsm.errors import InputFileError, TiledsmError
from tiledsm.workflows.sr_scores import RegionRule, compare_by_region, compare_on_common, regions_from_truth

__all__ = ["MAX_TABLE_CELLS", "SRDSMTruth", "table_step", "truth_of", "dsm_tables", "score_tables", "with_tables",
           "write_blunder_map", "score"]

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


def dsm_tables(run_dir: Path, truth: SRDSMTruth, methods: Sequence[str]) -> dict:
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


# --------------------------------------------------------------------------- a finished run folder
def truth_of(run_dir: Path, recipe, truth: str | Path | None) -> SRDSMTruth:
    """The :class:`SRDSMTruth` of a finished run folder.

    ``truth`` (``--truth``): a synthetic scene folder (``scene.json``: its
    truth DSM, visible-ground mask and classes) or a reference DSM; default:
    the scene the run made (``scene/``), else the recipe's
    ``input.reference``, else none (the HR-pair DSM is the only reference).

    Raises
    ------
    InputFileError
        A truth that does not exist, or a folder that is neither a DSM nor
        a synthetic scene.
    """
    from tiledsm.evaluate.scenes import is_scene, open_scene

    if truth is None:
        if is_scene(run_dir / "scene"):
            truth = run_dir / "scene"
        elif recipe.input.reference:
            return SRDSMTruth(reference=recipe.input.reference)
        else:
            return SRDSMTruth()
    truth = Path(truth)
    if not truth.exists():
        raise InputFileError(f"{truth}: --truth: no such file or folder")
    if is_scene(truth):
        scene = open_scene(truth)
        return SRDSMTruth(truth=str(scene.truth_dsm), visible=str(scene.visible_mask), label=str(scene.truth_label))
    if truth.is_dir() and not (truth / ".zattrs").exists() and not (truth / "zarr.json").exists():
        raise InputFileError(f"{truth}: --truth: neither a reference DSM nor a synthetic scene folder (no scene.json)")
    return SRDSMTruth(reference=str(truth))


def with_tables(metrics: dict, scores: dict, reference: str | None = None) -> dict:
    """A run's ``metrics.json`` with its evaluation's rows (:func:`score`:
    ``dsms``, ``common``, ``table_step``, ``regions``) beside its own
    (``hr``, ``methods``): what :func:`tiledsm.workflows.sr_scores.markdown_report`
    renders."""
    import copy

    doc = copy.deepcopy(metrics)
    rows = scores["dsms"]
    doc["hr"].update(rows.get("hr", {}))
    for name, row in doc["methods"].items():
        row.update(rows.get(name, {}))
    doc.update({k: scores[k] for k in ("common", "table_step", "regions") if k in scores})
    if reference is not None:
        doc["reference"] = reference
    return doc


def score(run_dir: Path, truth: str | Path | None = None) -> dict:
    """Score a finished ``sr_dsm`` run folder (module notes).

    Returns
    -------
    dict
        ``truth`` (where it came from; None: the HR-pair DSM only), the
        :func:`dsm_tables`: ``dsms`` (``dsms[name][table]``, their
        ``scores``), ``common``, ``table_step``, ``regions``; and ``products``
        (``evaluation/report.md``, ``evaluation/blunders.png``).

    Raises
    ------
    InputFileError
        A DSM of the run is missing (it did not finish), or a truth that
        does not exist or is neither kind.
    NoOverlapError, GridError
        A given truth that covers none of the run's grid (the message names
        ``--truth``).
    """
    import json

    from tiledsm.evaluate import resolved_recipe
    from tiledsm.io import atomic_path
    from tiledsm.workflows.sr_dsm import SRDSMRecipe
    from tiledsm.workflows.sr_scores import markdown_report

    run_dir = Path(run_dir)
    recipe = resolved_recipe(run_dir, SRDSMRecipe)
    methods = list(recipe.sr.models)
    for path in [run_dir / "hr" / "dsm.zarr", *(method_dsm(run_dir, m) for m in methods), run_dir / "metrics.json"]:
        if not path.exists():
            raise InputFileError(f"{run_dir}: no {path.relative_to(run_dir)}: the sr_dsm run did not finish "
                                 "(nothing to score)")
    known = truth_of(run_dir, recipe, truth)
    folder = run_dir / "evaluation"
    try:
        tables = dsm_tables(run_dir, known, methods)
        folder.mkdir(exist_ok=True)
        png = write_blunder_map(run_dir, known, methods, folder / "blunders.png")
    except TiledsmError as exc:  # a given truth that does not fit this run: say it is the truth's fault
        if truth is None:
            raise
        raise type(exc)(f"--truth: {exc}") from None
    source = Path(known.truth).parent if known.truth else known.reference
    doc = {"truth": None if source is None else str(source), "dsms": tables["scores"],
           **{k: v for k, v in tables.items() if k != "scores"}}
    metrics = json.loads((run_dir / "metrics.json").read_text())
    with atomic_path(folder / "report.md") as tmp:
        Path(tmp).write_text(markdown_report(with_tables(metrics, doc, known.reference)))
    doc["products"] = [str(p.relative_to(run_dir)) for p in (folder / "report.md", Path(png))]
    return doc
