"""The run contract of ``tiledsm ortho``, through the command in a
subprocess: run.log, recipe.resolved.yaml (which ``tiledsm run`` accepts
and reproduces) and metrics.json; a second run into a folder the first
holds is refused; a run SIGKILLed midway resumes its finished chunks and
gives the ortho of an uninterrupted run, bit for bit.

One small synthetic scene (256 DSM cells, tests/ortho/conftest.py), the
ortho at 0.25 m (512 x 512 cells) in chunks of 64: 64 chunks, computed one
at a time (synchronous scheduler) so that a kill lands midway."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from tests.run_contract import kill, ok, refused_while_held, run, start, temporaries, tiledsm, wait_until
from tiledsm.io import open_product

TOTAL = 64  # chunks of 64 over the 512 x 512 ortho cells
SLOW = ("--resolution", "0.25", "--chunk", "64", "--kernel", "cs", "--scheduler", "synchronous", "--no-progress")


def ortho_cmd(scene, out, *extra):
    return tiledsm("ortho", scene.views[0], "--dsm", scene.truth_dsm, "--out", out, *SLOW, *extra)


def metrics(out) -> dict:
    return json.loads((out / "metrics.json").read_text())


def done_count(partial) -> int:
    """Chunks marked done in a partial store (0 while it is not readable)."""
    import zarr

    try:
        return int(np.asarray(zarr.open_array(store=str(partial), path="_progress/done", mode="r")[...]).sum())
    except Exception:  # noqa: BLE001 - not created yet, or being created
        return 0


@pytest.fixture(scope="module")
def uninterrupted(ortho_scene, tmp_path_factory):
    """A folder with a finished, uninterrupted run."""
    out = tmp_path_factory.mktemp("uninterrupted") / "o"
    ok(run(ortho_cmd(ortho_scene, out)))
    return out


def test_a_run_writes_its_log_resolved_recipe_and_metrics(uninterrupted, tmp_path):
    out = uninterrupted
    assert "running pipeline ortho into" in (out / "run.log").read_text()
    m = metrics(out)
    assert m["pipeline"] == "ortho" and m["shape"] == [512, 512] and m["resolution_m"] == 0.25
    assert m["timings"]["chunks"] == {"chunks_total": TOTAL, "chunks_reused": 0, "chunks_computed": TOTAL}
    stored = open_product(out / "ortho.zarr").values
    assert abs(m["valid_share"] - float(np.isfinite(stored).mean())) < 1e-12
    resolved = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    assert resolved["pipeline"] == "ortho" and resolved["grid"] == {
        "resolution": 0.25, "bounds": None, "crs": None, "chunk": 64}
    assert resolved["ortho"]["kernel"] == "cs"
    # `tiledsm run` on the resolved recipe makes the same ortho
    again = tmp_path / "again"
    ok(run(tiledsm("run", out / "recipe.resolved.yaml", "--out", again, "--scheduler", "synchronous", "--no-progress")))
    np.testing.assert_array_equal(open_product(again / "ortho.zarr").values, stored)
    assert yaml.safe_load((again / "recipe.resolved.yaml").read_text()) == resolved
    assert metrics(again)["timings"]["chunks"]["chunks_computed"] == TOTAL


@pytest.mark.slow
def test_a_second_run_into_a_held_folder_is_refused(ortho_scene, uninterrupted, tmp_path):
    out = tmp_path / "busy"
    refused_while_held(ortho_cmd(ortho_scene, out), ortho_cmd(ortho_scene, out, "--kernel", "nn"), out, "ortho",
                       tmp_path / "first.log")
    np.testing.assert_array_equal(open_product(out / "ortho.zarr").values,
                                  open_product(uninterrupted / "ortho.zarr").values)
    assert metrics(out)["timings"]["chunks"]["chunks_computed"] == TOTAL


@pytest.mark.slow
def test_a_killed_run_resumes_its_finished_chunks(ortho_scene, uninterrupted, tmp_path):
    out = tmp_path / "killed"
    partial = out / "ortho.zarr.partial"
    p = start(ortho_cmd(ortho_scene, out), tmp_path / "first.log")
    try:
        wait_until(p, lambda: done_count(partial) >= 3, "3 chunks were written", tmp_path / "first.log")
    finally:
        kill(p)
    assert p.returncode < 0  # killed, not finished
    done = done_count(partial)
    assert 3 <= done < TOTAL
    assert not (out / "ortho.zarr").exists()
    assert not any((out / n).exists() for n in ("metrics.json", "recipe.resolved.yaml", "ortho.json", "ortho.tif"))
    r = ok(run(ortho_cmd(ortho_scene, out)))  # the dead run's lock is stale and taken over
    assert metrics(out)["timings"]["chunks"] == {"chunks_total": TOTAL, "chunks_reused": done,
                                                 "chunks_computed": TOTAL - done}
    assert f"reused {done} of {TOTAL} chunks" in r.stdout
    np.testing.assert_array_equal(open_product(out / "ortho.zarr").values,
                                  open_product(uninterrupted / "ortho.zarr").values)
    assert not partial.exists() and not (out / ".tiledsm.lock").exists() and not temporaries(out)
    resolved = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    assert {**resolved, "name": "o"} == yaml.safe_load((uninterrupted / "recipe.resolved.yaml").read_text())


def test_messages_name_the_option_or_the_recipe_field(ortho_scene, tmp_path, capsys):
    """The command's bad value names its option (from the spec's metadata);
    the same fault in a recipe names the recipe field."""
    from tiledsm.cli import main

    base = ["ortho", str(ortho_scene.views[0]), "--dsm", str(ortho_scene.truth_dsm), "--out", str(tmp_path / "o")]
    assert main(base + ["--chunk", "8"]) == 2
    assert "tiledsm ortho: error: --chunk: Input should be greater than or equal to 16" in capsys.readouterr().err
    recipe = tmp_path / "ortho.yaml"
    recipe.write_text(yaml.safe_dump({"pipeline": "ortho", "input": {"image": str(ortho_scene.views[0]),
                                                                     "dsm": str(tmp_path / "nope.tif")}}))
    assert main(["run", str(recipe), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "nope.tif: input.dsm: no such file" in err and "--dsm" not in err
    assert not (tmp_path / "o").exists() and not (tmp_path / "r").exists()
