"""Evaluation apart from production: score a finished run folder against a
truth.

A run (``tiledsm run``, ``tiledsm dsm``, ``tiledsm displace`` ...) leaves
its products, ``metrics.json`` and ``recipe.resolved.yaml`` in its folder
and knows nothing of a truth. :func:`evaluate_run` reads the folder's
resolved recipe to know its pipeline, hands the folder and the truth (a
synthetic scene the run made, ``scene/``, or one given) to that
pipeline's scorer and writes what it returns into ``evaluation.json``
beside the products (and, where a person would rather look, a quick-look
PNG or the truth on the product's grid under ``evaluation/``).

:data:`SCORERS` maps a pipeline name to its scorer, ``"module:function"``,
imported only when a run of that pipeline is scored. A scorer is
``score(run_dir: Path, truth: str | Path | None) -> dict`` and raises a
:class:`~tiledsm.errors.TiledsmError` naming the file and the problem
when the truth does not fit the run.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Callable

from tiledsm.errors import InputFileError

__all__ = ["SCORERS", "EVALUATION", "pipeline_of", "resolved_recipe", "scorer_of", "evaluate_run"]

#: pipeline name -> its scorer, "module:function" (imported when used)
SCORERS: dict[str, str] = {
    "dsm": "tiledsm.evaluate.dsm:score",
    "displace": "tiledsm.evaluate.displacement:score",
    "deformation": "tiledsm.evaluate.deformation:score",
    "sr_dsm": "tiledsm.evaluate.sr_dsm:score",
}

#: the file :func:`evaluate_run` writes into the run folder
EVALUATION = "evaluation.json"


def pipeline_of(run_dir: str | Path) -> str:
    """The pipeline a finished run folder holds (its ``recipe.resolved.yaml``).

    Raises
    ------
    InputFileError
        No such folder, or not a finished tiledsm run.
    """
    import yaml

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputFileError(f"{run_dir}: RUN_DIR: no such folder")
    resolved = run_dir / "recipe.resolved.yaml"
    if not resolved.is_file():
        raise InputFileError(f"{run_dir}: RUN_DIR: not a finished tiledsm run (no recipe.resolved.yaml)")
    try:
        doc = yaml.safe_load(resolved.read_text())
    except yaml.YAMLError:
        doc = None
    name = doc.get("pipeline") if isinstance(doc, dict) else None
    if not isinstance(name, str):
        raise InputFileError(f"{resolved}: RUN_DIR: names no pipeline")
    return name


def resolved_recipe(run_dir: str | Path, model):
    """The recipe a finished run folder ran (its ``recipe.resolved.yaml``),
    read through ``model`` (a field added since that run takes its default).

    Raises
    ------
    InputFileError
        The file does not fit ``model`` (a folder of another pipeline or
        version).
    """
    import yaml
    from pydantic import ValidationError

    resolved = Path(run_dir) / "recipe.resolved.yaml"
    try:
        return model.model_validate(yaml.safe_load(resolved.read_text()))
    except (yaml.YAMLError, ValidationError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputFileError(f"{resolved}: RUN_DIR: not a recipe this version reads ({first})") from None


def scorer_of(pipeline: str, run_dir: str | Path = "RUN_DIR") -> Callable[..., dict]:
    """The scorer of ``pipeline`` (:data:`SCORERS`), imported now
    (``run_dir``: the folder the messages name).

    Raises
    ------
    InputFileError
        No scorer for that pipeline, or its module is not installed.
    """
    target = SCORERS.get(pipeline)
    if target is None:
        raise InputFileError(f"{run_dir}: RUN_DIR: a {pipeline} run has no truth to be scored against "
                             f"(scored pipelines: {', '.join(sorted(SCORERS))})")
    module, _, function = target.partition(":")
    try:
        return getattr(importlib.import_module(module), function)
    except ModuleNotFoundError as exc:
        if exc.name != module:  # a dependency of the scorer is missing: that is a bug, not the user's input
            raise
        raise InputFileError(f"{run_dir}: RUN_DIR: the scorer of {pipeline} runs ({module}) is not in this "
                             "installation") from None


def evaluate_run(run_dir: str | Path, truth: str | Path | None = None) -> dict:
    """Score a finished run folder against ``truth`` (default: the
    synthetic scene the run made) and write ``evaluation.json`` into it.

    Returns the document written: ``pipeline``, ``run``, and the scorer's
    scores under ``scores``.

    Raises
    ------
    InputFileError, NoOverlapError, GridError
        Not a run folder, no scorer for its pipeline, or a truth that is
        missing or does not fit the run (the message names it). Nothing is
        written then.
    """
    from tiledsm.io import atomic_path

    run_dir = Path(run_dir).expanduser().resolve()
    pipeline = pipeline_of(run_dir)
    scores = scorer_of(pipeline, run_dir)(run_dir, None if truth is None else Path(truth).expanduser().resolve())
    doc = {"pipeline": pipeline, "run": str(run_dir), "scores": scores}
    with atomic_path(run_dir / EVALUATION) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2, default=float))
    return doc
