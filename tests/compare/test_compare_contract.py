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
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.compare.conftest import centres, terrain, write_tif
from tests.run_contract import killed_when, ok, refused_while_held, run
from tiledsm.io import open_product

pytestmark = pytest.mark.slow  # four comparisons in subprocesses: ~2 min on the 2-core machine

N = 1536
PRODUCTS = ["dh.png", "dh.tif", "dh.zarr", "dh_hist.png", "dh_slope_classes.png", "metrics.json",
            "recipe.resolved.yaml", "report.html", "run.log"]


def compare_cmd(pair: tuple[Path, Path], out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "compare", str(pair[0]), str(pair[1]), "--out", str(out),
            "--chunks", "256", "--no-progress", *extra]


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
    refused_while_held(compare_cmd(pair, out), compare_cmd(pair, out, "--coreg", "none"), out, "compare",
                       tmp_path / "first.log")
    np.testing.assert_array_equal(dh(out), dh(finished))
    assert metrics(out) == metrics(finished)


def test_a_killed_run_reruns_to_the_same_products(pair, finished, tmp_path):
    out = tmp_path / "killed"
    cmd = compare_cmd(pair, out)
    # killed while the products are written into their staging folder: mid-way
    killed_when(cmd, lambda: out.is_dir() and any(q.name.startswith(".compare.tmp-") for q in out.iterdir()),
                "the staging folder", tmp_path / "first.log")
    left = sorted(q.name for q in out.iterdir())
    assert not set(left) & {"dh.zarr", "dh.tif", "metrics.json", "recipe.resolved.yaml", "report.html"}, left
    assert any(n.startswith(".compare.tmp-") for n in left), left
    ok(run(cmd))  # the dead run's lock is stale: taken over, its staging swept
    assert sorted(q.name for q in out.iterdir()) == PRODUCTS
    np.testing.assert_array_equal(dh(out), dh(finished))
    assert metrics(out) == metrics(finished)
