"""The documentation cannot drift from the code.

- The generated references (``docs/_generate.py``, rendered into the site at
  build time) list every ``tiledsm`` command with every option, and every
  field of every pipeline's recipe; checked against the parsers and the
  pydantic models walked here independently.
- Every ``tiledsm ...`` command line shown in README.md and docs/ parses with
  today's parsers, and every recipe shown validates against its pipeline.
- The command lines that run on synthetic scenes are run, as typed, and the
  products the guides show (the quick-looks) are checked against the scene's
  truth.
- The accuracy, speed and results pages render from ``benchmarks/results``.

The strict site build itself (broken links, anchors, docstrings) runs in
``make docs``, which ``make test`` runs before pytest.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
PAGES = sorted(DOCS.rglob("*.md")) + [REPO / "README.md"]
#: what ``$S`` stands for in the guides
SHELL_VARS = {"$S": "../shared/data/s2p_pair"}
#: recipes whose ``tiledsm run`` the tests run as shown (the others take minutes to hours)
RUN_RECIPES = {"recipes/demo.yaml", "recipes/deformation.yaml"}


def _generator():
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS / "_generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def gen():
    return _generator()


# ---------------------------------------------------------------------------- generated references


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    from tiledsm.cli import build_parser

    action = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _section(page: str, heading: str) -> str:
    """The text of a ``## heading`` section of a markdown page."""
    start = page.index(f"\n## {heading}\n")
    end = page.find("\n## ", start + 1)
    return page[start: end if end >= 0 else len(page)]


def test_cli_reference_lists_every_command_and_option(gen):
    page = gen.cli_reference()
    commands = _subparsers()
    assert len(commands) >= 10 and {"dsm", "run", "compare", "ortho", "orient", "sr"} <= set(commands)
    for name, parser in commands.items():
        section = _section(page, f"tiledsm {name}")
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for flag in action.option_strings or [action.metavar or action.dest]:
                assert f"`{flag}" in section, f"tiledsm {name}: {flag} missing from the CLI reference"
            if action.help and action.help != argparse.SUPPRESS:
                assert " ".join(action.help.split())[:40].replace("|", "\\|") in section, (name, action.dest)


def _nested_models(annotation):
    """The pydantic models in a field's annotation (``Optional[X]``, ``list[X]``...)."""
    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in typing.get_args(annotation) for m in _nested_models(a)]


def _walk(model, prefix=""):
    """Every field path of a pydantic model, nested models expanded."""
    for name, field in model.model_fields.items():
        path = prefix + name
        yield path
        for sub in _nested_models(field.annotation):
            yield from _walk(sub, path + ".")


def test_recipe_reference_lists_every_field_of_every_pipeline(gen):
    from tiledsm.pipelines import PIPELINES
    from tiledsm.sr.train import TrainConfig

    page = gen.recipe_reference()
    # dict fields validated by name against a dataclass: its fields are recipe fields too
    # (match.params is a model, SGVLLParams: walked as a section)
    held = {"train": TrainConfig}
    counted = 0
    for name, pipeline in PIPELINES.items():
        section = _section(page, f"pipeline: {name}")
        paths = list(_walk(pipeline.recipe))
        paths += [f"{p}.{f.name}" for p, cls in held.items() if p in paths for f in dataclasses.fields(cls)]
        for path in paths:
            assert f"| `{path}` |" in section, f"pipeline {name}: {path} missing from the recipe reference"
        counted += len(paths)
    assert counted > 150  # every pipeline walked, nested sections included


def test_fallback_descriptions_name_existing_fields(gen):
    from tiledsm.pipelines import PIPELINES

    models, stack = {}, [p.recipe for p in PIPELINES.values()]
    while stack:
        m = stack.pop()
        models[m.__name__] = m
        for f in m.model_fields.values():
            stack += _nested_models(f.annotation)
    for key in gen.FALLBACK_DESCRIPTIONS:
        if "." in key:
            model, field = key.split(".")
            assert model in models and field in models[model].model_fields, key


def test_recipe_reference_states_types_defaults_and_descriptions(gen):
    page = gen.recipe_reference()
    dsm = _section(page, "pipeline: dsm")
    assert "| `grid.chunk` | int | `512` | chunk side, cells (>= 32) |" in dsm
    assert "| `match.params.zncc_min` | float | `0.25` |" in dsm
    assert "| `input` | InputSpec | required |" in dsm
    # a field of a nested parameter model (SGVLLParams), with its unit
    assert re.search(r"\| `match.params.speckle_slope` \| float \| `60.0` \| [^|]*degrees", dsm)


def test_api_reference_covers_every_module(gen):
    pages = gen.api_pages()
    listed = "\n".join(pages.values())
    for path in (REPO / "tiledsm").rglob("*.py"):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__main__":
            continue
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        assert f"::: {module}\n" in listed, module


def test_measurement_pages_render_every_results_file(gen):
    pages = gen.pages()
    results = pages["reference/results.md"]
    for path in sorted((REPO / "benchmarks" / "results").glob("*.json")):
        assert f"\n## {path.name}\n" in results, path.name
    demo = json.loads((REPO / "benchmarks" / "results" / "demo.json").read_text())
    assert f"| {demo['vs_reference_visible']['nmad']:.3f} |" in pages["reference/accuracy.md"]
    assert "Mcells/s" in pages["reference/speed.md"]


def test_no_results_file_named_by_a_stop_or_a_run():
    names = [p.name for p in (REPO / "benchmarks" / "results").iterdir()]
    assert not [n for n in names if re.search(r"stop\d|_run\d", n)]


def test_benchmarks_readme_names_every_script_with_its_command_and_output():
    text = (REPO / "benchmarks" / "README.md").read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `(\w+\.py)` \|.*$", text, re.M)}
    for script in sorted((REPO / "benchmarks").glob("*.py")):
        assert script.name in rows, f"benchmarks/README.md does not name {script.name}"
        if not script.name.startswith("_"):
            assert f"benchmarks/{script.name}" in rows[script.name] and ".json" in rows[script.name], script.name


def test_make_test_builds_the_docs_in_strict_mode():
    make = (REPO / "Makefile").read_text()
    assert re.search(r"^test: .*\bdocs\b", make, re.M)
    assert re.search(r"^docs:.*\n\t.*mkdocs build --strict", make, re.M)
    assert "strict: true" in (REPO / "mkdocs.yml").read_text()


def test_readme_is_short():
    assert len((REPO / "README.md").read_text().splitlines()) <= 300


def test_quicklooks_shown_by_the_guides_are_small_and_present():
    shown = set()
    for page in PAGES:
        shown |= set(re.findall(r"\]\(\.\./images/([\w.]+\.png)\)", page.read_text()))
    assert {"demo_dsm.png", "deformation_dh.png", "displacement.png"} <= shown
    for name in shown:
        assert (DOCS / "images" / name).stat().st_size < 300_000, name


# ---------------------------------------------------------------------------- the commands the guides show


def _code_blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, re.S)


def _command_lines(text: str) -> list[list[str]]:
    """``tiledsm`` command lines of a page's bash blocks, as argv after ``tiledsm``."""
    out = []
    for block in _code_blocks(text, "bash"):
        block = block.replace("\\\n", " ")
        for line in block.splitlines():
            line = line.split(" #")[0].strip()
            for prefix in (".venv/bin/tiledsm ", "tiledsm "):
                if line.startswith(prefix):
                    for var, value in SHELL_VARS.items():
                        line = line.replace(var, value)
                    out.append(shlex.split(line[len(prefix):]))
    return out


def _all_commands() -> list[tuple[str, list[str]]]:
    seen, out = set(), []
    for page in PAGES:
        for argv in _command_lines(page.read_text()):
            key = tuple(argv)
            if key not in seen:
                seen.add(key)
                out.append((str(page.relative_to(REPO)), argv))
    return out


def test_every_command_line_in_the_docs_parses():
    from tiledsm.cli import build_parser

    commands = _all_commands()
    assert len(commands) > 20
    for page, argv in commands:
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            pytest.fail(f"{page}: tiledsm {' '.join(argv)} does not parse")


def test_every_recipe_shown_in_the_docs_validates():
    from tiledsm.pipelines import PIPELINES

    shown = 0
    for page in PAGES:
        for block in _code_blocks(page.read_text(), "yaml"):
            doc = yaml.safe_load(block)
            if isinstance(doc, dict) and "pipeline" in doc:
                PIPELINES[doc["pipeline"]].recipe.model_validate(doc)
                shown += 1
    assert shown >= 2


def _runs_on_synthetic_scenes(argv: list[str]) -> bool:
    """A command whose every file is made by the docs' own commands (under
    ``runs/``) or is a recipe the tests run; no cluster address."""
    for token in argv:
        if token.startswith(("tcp://", "../")):
            return False
        if re.search(r"\.(tif|yaml|gtx|csv|geojson|hgt|zarr)$", token) and not token.startswith("runs/"):
            if token not in RUN_RECIPES:
                return False
    return argv[0] in ("synth", "degrade", "sr", "run")


@pytest.mark.slow
def test_guide_commands_on_synthetic_scenes_run_as_shown(tmp_path):
    """Each command line of the docs that runs on synthetic scenes, once, in
    order, as a user types it; then the products the guides show."""
    runnable = [(page, argv) for page, argv in _all_commands() if _runs_on_synthetic_scenes(argv)]
    shown = {" ".join(argv) for _, argv in runnable}
    assert "run recipes/demo.yaml --out runs/demo" in shown
    assert "run recipes/deformation.yaml --out runs/deformation" in shown
    assert any(a[0] == "sr" for _, a in runnable) and any(a[0] == "synth" for _, a in runnable)
    (tmp_path / "recipes").symlink_to(REPO / "recipes")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for page, argv in runnable:
        done = subprocess.run([sys.executable, "-m", "tiledsm", *argv, *(["--no-progress"] if argv[0] in ("run", "sr") else [])],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, f"{page}: tiledsm {' '.join(argv)}\n{done.stderr[-2000:]}"
    runs = tmp_path / "runs"
    # make demo / the DSM guide: the hillshade and the error map, the DSM within the bounds against the truth
    demo = json.loads((runs / "demo" / "metrics.json").read_text())
    assert demo["vs_reference_visible"]["nmad"] <= 0.5 and demo["vs_reference_visible"]["completeness"] >= 0.95
    # the deformation and displacement guides: dh map, histogram, arrows, profiles; the throw against the truth
    deformation = runs / "deformation"
    for png in ("compare/dh.png", "compare/dh_hist.png", "displacement/displacement.png", "displacement/profiles.png",
                "../demo/dsm.png", "../demo/dsm_error.png"):
        assert (deformation / png).stat().st_size > 10_000, png
    # its scores against the truth: tiledsm evaluate on the finished folder, as the evaluate guide shows
    done = subprocess.run([sys.executable, "-m", "tiledsm", "evaluate", str(deformation)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    truth = json.loads((deformation / "evaluation.json").read_text())["scores"]["dh"]
    assert abs(truth["throw"]["error"]) <= 0.3
    # the SR quick start: the super-resolved image is twice the low-resolution one
    import rasterio

    with rasterio.open(runs / "sr" / "lr.tif") as lr, rasterio.open(runs / "sr" / "x2" / "sr.tif") as sr:
        assert (sr.width, sr.height) == (2 * lr.width, 2 * lr.height)
