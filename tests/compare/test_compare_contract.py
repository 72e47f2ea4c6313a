"""The run contract of ``tiledsm compare REF OTHER --out DIR``, through the
command (a subprocess, as users run it): the run files, the resolved recipe
that ``tiledsm run`` reproduces, the folder's lock, and a rerun after a
SIGKILL.

Two synthetic DSMs (1536² cells of 10 m, analytic terrain): OTHER is the
terrain sampled 1.3 rows and -0.7 columns further, plus 2 m, so the
co-registration's truth is ``dy_px = 1.3, dx_px = -0.7, dz = -2`` (the
convention of :mod:`tiledsm.compare.coreg`). A run takes ~15 s of compute
on the 2-core machine: long enough for a second process to meet the lock
and for a kill to land while the products are staged.
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

from tests.compare.conftest import centres, terrain, write_tif
from tiledsm.io import open_product

pytestmark = pytest.mark.slow  # four comparisons in subprocesses: ~2 min on the 2-core machine

N = 1536
PRODUCTS = ["dh.png", "dh.tif", "dh.zarr", "dh_hist.png", "dh_slope_classes.png", "metrics.json",
            "recipe.resolved.yaml", "report.html", "run.log"]


def compare_cmd(pair: tuple[Path, Path], out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "compare", str(pair[0]), str(pair[1]), "--out", str(out),
            "--chunks", "256", "--no-progress", *extra]


def run(cmd: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-2000:]}\n--- stderr\n{r.stderr[-3000:]}"
    return r


def wait_for(predicate, process: subprocess.Popen, what: str, timeout: float = 180) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert process.poll() is None, f"the run ended (rc {process.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.02)


def metrics(out: Path) -> dict:
    m = json.loads((out / "metrics.json").read_text())
    m.pop("timings_s")  # the only measure of the run itself
    return m


def dh(out: Path) -> np.ndarray:
    return np.asarray(open_product(out / "dh.zarr")["dh"].values)


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("pair")
    ref = terrain(*centres((N, N)))
    other = terrain(*centres((N, N), 1.3, -0.7)) + 2.0
    return write_tif(root / "ref.tif", ref), write_tif(root / "other.tif", other)


@pytest.fixture(scope="module")
def finished(pair, tmp_path_factory) -> Path:
    """An uninterrupted run."""
    out = tmp_path_factory.mktemp("finished") / "cmp"
    ok(run(compare_cmd(pair, out)))
    return out


def test_a_run_writes_its_run_files_and_run_reproduces_it(pair, finished, tmp_path):
    out = finished
    assert sorted(p.name for p in out.iterdir()) == PRODUCTS
    assert "running pipeline compare" in (out / "run.log").read_text()
    recipe = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    assert recipe["pipeline"] == "compare" and recipe["input"] == {"ref": str(pair[0]), "other": str(pair[1])}
    assert recipe["compare"]["chunk"] == 256 and recipe["compare"]["coreg"] == "nuth_kaab"
    m = metrics(out)
    assert m["warnings"] == []
    c = m["coregistration"]  # the analytic truth of the pair
    assert abs(c["dy_px"] - 1.3) < 0.01 and abs(c["dx_px"] + 0.7) < 0.01 and abs(c["dz"] + 2.0) < 0.01, c
    # the resolved recipe is a recipe: `tiledsm run` on it makes the same products
    again = tmp_path / "again"
    ok(run([sys.executable, "-m", "tiledsm", "run", str(out / "recipe.resolved.yaml"), "--out", str(again),
            "--scheduler", "threads", "--no-progress"]))
    assert sorted(p.name for p in again.iterdir()) == PRODUCTS
    np.testing.assert_array_equal(dh(again), dh(out))
    assert metrics(again) == m
    assert yaml.safe_load((again / "recipe.resolved.yaml").read_text()) == recipe


def test_a_second_run_into_a_held_folder_is_refused(pair, finished, tmp_path):
    out = tmp_path / "busy"
    with open(tmp_path / "first.log", "w") as log:
        first = subprocess.Popen(compare_cmd(pair, out), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            wait_for(lambda: (out / ".tiledsm.lock").exists(), first, "the lock")
            second = run(compare_cmd(pair, out, "--coreg", "none"), timeout=120)
            first_alive = first.poll() is None
            first.wait(timeout=300)
        finally:
            if first.poll() is None:
                os.killpg(first.pid, signal.SIGKILL)
                first.wait(timeout=30)
    assert second.returncode == 2 and "Traceback" not in second.stderr, second.stderr[-3000:]
    lines = [ln for ln in second.stderr.splitlines() if ln.startswith("tiledsm compare: error:")]
    assert len(lines) == 1 and str(out) in lines[0] and "another" in lines[0], second.stderr[-3000:]
    assert first_alive, f"the first run ended before the second was refused ({lines[0]})"
    assert first.returncode == 0, (tmp_path / "first.log").read_text()[-3000:]
    np.testing.assert_array_equal(dh(out), dh(finished))
    assert metrics(out) == metrics(finished)
    assert not (out / ".tiledsm.lock").exists()


def test_a_killed_run_reruns_to_the_same_products(pair, finished, tmp_path):
    out = tmp_path / "killed"
    cmd = compare_cmd(pair, out)
    with open(tmp_path / "first.log", "w") as log:
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:  # killed while the products are written into their staging folder: mid-way
            wait_for(lambda: out.is_dir() and any(q.name.startswith(".compare.tmp-") for q in out.iterdir()), p,
                     "the staging folder")
            os.killpg(p.pid, signal.SIGKILL)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL
    left = sorted(q.name for q in out.iterdir())
    assert not set(left) & {"dh.zarr", "dh.tif", "metrics.json", "recipe.resolved.yaml", "report.html"}, left
    assert any(n.startswith(".compare.tmp-") for n in left), left
    ok(run(cmd))  # the dead run's lock is stale: taken over, its staging swept
    assert sorted(q.name for q in out.iterdir()) == PRODUCTS
    np.testing.assert_array_equal(dh(out), dh(finished))
    assert metrics(out) == metrics(finished)
