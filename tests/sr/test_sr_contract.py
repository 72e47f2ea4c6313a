"""The run contract of ``tiledsm sr IMAGE OUT``, through the command (a
subprocess, as users run it): the run files, the resolved recipe that
``tiledsm run`` reproduces, the folder's lock, and a rerun after a SIGKILL.

One synthetic view (192² px, its RPC exact) super-resolved x2 by VDSR in
tiles of 48 px (16 tiles: ~15 s of compute on the 2-core machine, long
enough for a second process to meet the lock and for a kill to land while
``sr.tif`` is being written).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml

from tests.run_contract import killed_when, ok, refused_while_held, run
from tiledsm.geometry import RPC
from tiledsm.synth import make_scene

pytestmark = pytest.mark.slow  # four VDSR runs in subprocesses: ~2.5 min on the 2-core machine


def sr_cmd(image: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "sr", str(image), str(out), "--model", "vdsr", "--scale", "2",
            "--chunk", "48", "--scheduler", "synchronous", "--no-progress", *extra]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene"), size=192, gsd=0.5, bh=0.4, seed=5, views=2)


@pytest.fixture(scope="module")
def finished(scene, tmp_path_factory) -> Path:
    """An uninterrupted run."""
    out = tmp_path_factory.mktemp("finished") / "x2"
    ok(run(sr_cmd(scene.views[0], out)))
    return out


def test_a_run_writes_its_run_files_and_run_reproduces_it(scene, finished, tmp_path):
    out = finished
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "recipe.resolved.yaml", "run.log", "sr.tif"]
    assert "running pipeline sr" in (out / "run.log").read_text()
    recipe = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    assert recipe["pipeline"] == "sr" and recipe["input"]["image"] == str(scene.views[0].resolve())
    assert recipe["sr"]["model"] == "vdsr" and recipe["sr"]["scale"] == 2 and recipe["sr"]["chunk"] == 48
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["product"] == "sr.tif" and metrics["shape"] == [384, 384] and metrics["warnings"] == []
    with rasterio.open(scene.views[0]) as lr, rasterio.open(out / "sr.tif") as hr:
        assert (hr.height, hr.width) == (2 * lr.height, 2 * lr.width)
        want = RPC.from_gdal(lr.rpcs.to_dict()).scaled(2)  # the camera of the x2 grid, exact
        assert RPC.from_gdal(hr.rpcs.to_dict()) == RPC.from_gdal(want.to_gdal())
        assert hr.tags()["sr_model"] == "vdsr" and np.isfinite(hr.read(1)).all()
    # the resolved recipe is a recipe: `tiledsm run` on it makes the same file, byte for byte
    again = tmp_path / "again"
    ok(run([sys.executable, "-m", "tiledsm", "run", str(out / "recipe.resolved.yaml"), "--out", str(again),
            "--scheduler", "synchronous", "--no-progress"]))
    assert (again / "sr.tif").read_bytes() == (out / "sr.tif").read_bytes()
    assert yaml.safe_load((again / "recipe.resolved.yaml").read_text()) == recipe


def test_a_second_run_into_a_held_folder_is_refused(scene, finished, tmp_path):
    out = tmp_path / "busy"
    refused_while_held(sr_cmd(scene.views[0], out), sr_cmd(scene.views[0], out, "--model", "bicubic"), out, "sr",
                       tmp_path / "first.log")
    assert (out / "sr.tif").read_bytes() == (finished / "sr.tif").read_bytes()
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["sr"]["model"] == "vdsr"


def test_a_killed_run_reruns_to_the_same_bytes(scene, finished, tmp_path):
    out = tmp_path / "killed"
    cmd = sr_cmd(scene.views[0], out)
    # killed while sr.tif is being written (its temporary exists): mid-way
    killed_when(cmd, lambda: out.is_dir() and any(".sr.tif.tmp-" in q.name for q in out.iterdir()),
                "the product's temporary", tmp_path / "first.log")
    left = sorted(q.name for q in out.iterdir())
    assert "sr.tif" not in left and "metrics.json" not in left and "recipe.resolved.yaml" not in left, left
    assert any(".sr.tif.tmp-" in n for n in left), left
    ok(run(cmd))  # the dead run's lock is stale: taken over, its temporary swept
    assert sorted(q.name for q in out.iterdir()) == ["metrics.json", "recipe.resolved.yaml", "run.log", "sr.tif"]
    assert (out / "sr.tif").read_bytes() == (finished / "sr.tif").read_bytes()
