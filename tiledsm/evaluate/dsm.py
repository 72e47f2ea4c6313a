"""Scores of a ``pipeline: dsm`` run folder against a reference DSM or a
synthetic scene's truth.

The truth is a reference DSM (GeoTIFF/COG or zarr store, any CRS and
cell size: resampled bilinearly onto the DSM's grid) or a synthetic scene
(a folder with ``scene.json``, as ``tiledsm synth`` or a ``synth:`` run
writes it): its truth DSM, and its visible-ground mask for a second set
of statistics on the cells every view sees. Default: the scene the run
made (``scene/``), else the recipe's ``input.reference``.

The statistics (:func:`tiledsm.compare.accuracy.reference_accuracy`:
histogram reductions of :mod:`tiledsm.compare.stats`) are computed
chunk by chunk on the DSM's own chunks: no process holds the whole DSM or
reference. ``evaluation/dsm_error.png`` shows ``DSM - truth``.
"""

from __future__ import annotations

import json
from pathlib import Path

from tiledsm.errors import InputFileError, TiledsmError

__all__ = ["score", "reference_of"]


def reference_of(run_dir: Path, truth: str | Path | None) -> tuple[Path, Path | None]:
    """``(reference DSM, visible mask or None)`` of ``truth`` (module notes).

    Raises
    ------
    InputFileError
        The truth is missing, or none is given and the run has none.
    """
    import yaml

    if truth is None:
        if (run_dir / "scene" / "scene.json").is_file():
            truth = run_dir / "scene"
        else:
            recipe = yaml.safe_load((run_dir / "recipe.resolved.yaml").read_text())
            truth = ((recipe.get("input") or {}).get("reference"))
            if truth is None:
                raise InputFileError(f"{run_dir}: the run has no reference DSM and made no synthetic scene: give "
                                     "--truth (a reference DSM or a synthetic scene folder)")
    truth = Path(truth)
    if not truth.exists():
        raise InputFileError(f"{truth}: --truth: no such file or folder")
    scene = truth / "scene.json" if truth.is_dir() else truth
    if scene.name == "scene.json" and scene.is_file():
        doc = json.loads(scene.read_text())["truth"]
        return scene.parent / doc["dsm"], scene.parent / doc["visible_mask"]
    if truth.is_dir() and not (truth / ".zattrs").exists() and not (truth / "zarr.json").exists():
        raise InputFileError(f"{truth}: --truth: neither a DSM nor a synthetic scene folder (no scene.json)")
    return truth, None


def score(run_dir: Path, truth: str | Path | None = None) -> dict:
    """Statistics of ``dsm.zarr - truth`` for a finished dsm run (module
    notes): ``vs_reference`` (with the co-registered statistics) and, for a
    synthetic scene, ``vs_reference_visible``.

    Raises
    ------
    InputFileError
        No DSM in the run, or a truth that is missing or no DSM.
    NoOverlapError
        The truth covers no cell of the DSM.
    """
    from tiledsm.compare.accuracy import reference_accuracy
    from tiledsm.io import open_product
    from tiledsm.quicklook import quicklook
    from tiledsm.workflows.common import grid_chunk

    run_dir = Path(run_dir)
    if not (run_dir / "dsm.zarr").exists():
        raise InputFileError(f"{run_dir}: no dsm.zarr: the dsm run did not finish (nothing to score)")
    reference, mask = reference_of(run_dir, truth)
    height = open_product(run_dir / "dsm.zarr")["height"]
    chunks = grid_chunk(height)
    try:
        doc: dict = {"truth": str(reference)}
        doc["vs_reference"], error = reference_accuracy(height, reference, chunks=chunks, coregister=True)
        if mask is not None:
            doc["visible_mask"] = str(mask)
            doc["vs_reference_visible"], _ = reference_accuracy(height, reference, mask, chunks=chunks)
    except TiledsmError as exc:  # the truth does not fit this run: say it is the truth's fault
        raise type(exc)(f"--truth: {exc}") from None
    r0, r1, c0, c1 = error.attrs["window"]
    (run_dir / "evaluation").mkdir(exist_ok=True)
    png = quicklook(error, run_dir / "evaluation" / "dsm_error.png", kind="difference", title="DSM - truth (m)",
                    dsm=height[r0:r1, c0:c1])
    doc["products"] = [str(Path(png).relative_to(run_dir))]
    return doc
