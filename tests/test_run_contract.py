"""The run contract of ``tiledsm run RECIPE --out DIR``, through the command
(a subprocess): the run files and a resolved recipe that reproduces the
run, and the folder's lock against a second ``tiledsm run``. (A run killed
mid-way and rerun is ``tests/test_resume.py``'s
``test_killed_run_resumes_its_finished_chunks``, through ``tiledsm run``
too.)

A ``pipeline: dsm`` recipe on a small synthetic pair (384² px, as tests/test_resume.py) on its truth
grid, in chunks of 64 cells.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.run_contract import ok, refused_while_held, run
from tiledsm.io import open_product
from tiledsm.synth import make_scene

pytestmark = pytest.mark.slow  # four small DSM runs in subprocesses


def run_cmd(recipe: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "run", str(recipe), "--out", str(out), "--scheduler", "synchronous",
            "--no-progress"]


def heights(out: Path) -> np.ndarray:
    return open_product(out / "dsm.zarr")["height"].values


@pytest.fixture(scope="module")
def recipe(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scene")
    scene = make_scene(root / "scene", size=384, gsd=0.5, bh=0.4, seed=4, views=2)
    path = root / "dsm.yaml"
    path.write_text(yaml.safe_dump({
        "pipeline": "dsm", "name": "contract", "input": {"images": [str(v) for v in scene.views]},
        "grid": {"like": str(scene.truth_dsm), "chunk": 64}, "match": {"levels": 2},
        "output": {"cog": False, "quicklook": False},
    }))
    return path


@pytest.fixture(scope="module")
def finished(recipe, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("finished") / "dsm"
    ok(run(run_cmd(recipe, out)))
    return out


def test_a_run_writes_its_run_files_and_its_resolved_recipe_reproduces_it(recipe, finished, tmp_path):
    assert {"run.log", "metrics.json", "recipe.resolved.yaml", "dsm.zarr"} <= {p.name for p in finished.iterdir()}
    assert "running pipeline dsm" in (finished / "run.log").read_text()
    resolved = yaml.safe_load((finished / "recipe.resolved.yaml").read_text())
    given = yaml.safe_load(recipe.read_text())
    assert resolved["pipeline"] == "dsm" and resolved["input"]["images"] == given["input"]["images"]
    assert resolved["grid"]["chunk"] == 64 and resolved["match"]["levels"] == 2
    metrics = json.loads((finished / "metrics.json").read_text())
    assert metrics["timings"]["chunks"]["chunks_computed"] == metrics["timings"]["chunks"]["chunks_total"] > 1
    h = heights(finished)
    assert np.isfinite(h).mean() > 0.7  # the truth grid's borders are outside a view
    again = tmp_path / "again"
    ok(run(run_cmd(finished / "recipe.resolved.yaml", again)))
    np.testing.assert_array_equal(heights(again), h)
    assert yaml.safe_load((again / "recipe.resolved.yaml").read_text()) == resolved


def test_a_second_run_into_a_held_folder_is_refused(recipe, finished, tmp_path):
    out = tmp_path / "busy"
    other = tmp_path / "other.yaml"  # another recipe into the same folder
    other.write_text(recipe.read_text().replace("levels: 2", "levels: 1"))
    refused_while_held(run_cmd(recipe, out), run_cmd(other, out), out, "run", tmp_path / "first.log")
    np.testing.assert_array_equal(heights(out), heights(finished))
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["match"]["levels"] == 2
