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
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tiledsm.io import open_product
from tiledsm.synth import make_scene

pytestmark = pytest.mark.slow  # four small DSM runs in subprocesses


def run_cmd(recipe: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "run", str(recipe), "--out", str(out), "--scheduler", "synchronous",
            "--no-progress"]


def run(cmd: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-2000:]}\n--- stderr\n{r.stderr[-3000:]}"
    return r


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
    with open(tmp_path / "first.log", "w") as log:
        first = subprocess.Popen(run_cmd(recipe, out), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + 180
            while not (out / ".tiledsm.lock").exists():
                assert first.poll() is None, "the first run ended before taking the lock"
                assert time.monotonic() < deadline, "no lock within 180 s"
                time.sleep(0.02)
            second = run(run_cmd(other, out), timeout=120)
            first_alive = first.poll() is None
            first.wait(timeout=300)
        finally:
            if first.poll() is None:
                os.killpg(first.pid, signal.SIGKILL)
                first.wait(timeout=30)
    assert second.returncode == 2 and "Traceback" not in second.stderr, second.stderr[-3000:]
    lines = [ln for ln in second.stderr.splitlines() if ln.startswith("tiledsm run: error:")]
    assert len(lines) == 1 and str(out) in lines[0] and "another" in lines[0], second.stderr[-3000:]
    assert first_alive, f"the first run ended before the second was refused ({lines[0]})"
    assert first.returncode == 0, (tmp_path / "first.log").read_text()[-3000:]
    np.testing.assert_array_equal(heights(out), heights(finished))
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["match"]["levels"] == 2
