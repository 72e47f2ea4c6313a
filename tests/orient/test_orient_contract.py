"""The run contract of ``tiledsm orient``, through the command in a
subprocess: run.log, recipe.resolved.yaml (which ``tiledsm run`` accepts
and reproduces) and metrics.json; a second run into a folder the first
holds is refused; a run SIGKILLed midway leaves no report, and the same
command then completes with the products of an uninterrupted run, bit for
bit (an orientation takes seconds: it is computed again, not resumed).

The rendered 512-px pair with injected biases of tests/orient/conftest.py,
4 GCPs, tie points in 4 tiles of 256 px on the synchronous scheduler."""

from __future__ import annotations

import json
import shutil

import pytest
import yaml
from orient_cases import write_gcp_files

from tests.run_contract import (
    error_line, kill, ok, refused_while_held, run, start, temporaries, tiledsm, wait_until,
)

#: products compared byte for byte (orient.json apart: it holds timings)
EXACT = ("view_0.tif", "view_0_RPC.TXT", "view_1.tif", "view_1_RPC.TXT", "residuals.csv")


@pytest.fixture(scope="module")
def case(scene2):
    info, true, biased, h, root = scene2
    gcps, _ = write_gcp_files(true, [p.name for p in biased], root)
    return biased, gcps


def orient_cmd(case, out, *extra):
    biased, gcps = case
    return tiledsm("orient", *biased, "--gcps", gcps, "--out", out, "--tile", "256", "--scheduler", "synchronous",
                   "--no-progress", *extra)


def report(out) -> dict:
    """``orient.json`` without its timings, the run folder's name replaced."""
    doc = json.loads((out / "orient.json").read_text().replace(str(out), "OUT"))
    doc.pop("timings_s")
    return doc


def same_products(a, b) -> None:
    for name in EXACT:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert report(a) == report(b)


@pytest.fixture(scope="module")
def uninterrupted(case, tmp_path_factory):
    out = tmp_path_factory.mktemp("uninterrupted") / "o"
    ok(run(orient_cmd(case, out)))
    return out


def test_a_run_writes_its_log_resolved_recipe_and_metrics(uninterrupted, tmp_path):
    out = uninterrupted
    assert "running pipeline orient into" in (out / "run.log").read_text()
    m = json.loads((out / "metrics.json").read_text())
    doc = json.loads((out / "orient.json").read_text())
    assert m["pipeline"] == "orient"
    assert {k: m[k] for k in ("gcp_rms_px", "check_rms_px", "tie_relative_rms_px", "n_tracks", "datum")} == {
        k: doc[k] for k in ("gcp_rms_px", "check_rms_px", "tie_relative_rms_px", "n_tracks", "datum")}
    assert m["gcp_rms_px"]["after"] < 0.1 < 2.5 < m["gcp_rms_px"]["before"]  # 3 px injected, 0.05 px noise
    resolved = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    assert resolved["pipeline"] == "orient" and resolved["orient"]["tile"] == 256
    assert resolved["images"] == [str(p) for p in json.loads((out / "orient.json").read_text())["inputs"]["images"]]
    again = tmp_path / "o"
    ok(run(tiledsm("run", out / "recipe.resolved.yaml", "--out", again, "--scheduler", "synchronous", "--no-progress")))
    same_products(again, out)
    assert yaml.safe_load((again / "recipe.resolved.yaml").read_text()) == resolved


@pytest.mark.slow
def test_a_second_run_into_a_held_folder_is_refused(case, uninterrupted, tmp_path):
    out = tmp_path / "o"
    refused_while_held(orient_cmd(case, out), orient_cmd(case, out, "--model", "shift"), out, "orient",
                       tmp_path / "first.log")
    same_products(out, uninterrupted)


@pytest.mark.slow
def test_a_killed_run_completes_when_run_again(case, uninterrupted, tmp_path):
    out = tmp_path / "o"

    def writing() -> bool:  # the first image's copy (or its temporary) is being written
        return out.is_dir() and any(p.name.lstrip(".").startswith("view_0") for p in out.iterdir())

    p = start(orient_cmd(case, out), tmp_path / "first.log")
    try:
        wait_until(p, writing, "the products were being written", tmp_path / "first.log")
    finally:
        kill(p)
    assert p.returncode < 0  # killed, not finished
    assert not any((out / n).exists() for n in ("orient.json", "metrics.json", "recipe.resolved.yaml"))
    ok(run(orient_cmd(case, out)))  # the dead run's lock is stale and taken over
    same_products(out, uninterrupted)
    assert not (out / ".tiledsm.lock").exists() and not temporaries(out)


def test_messages_name_the_option_or_the_recipe_field(case, tmp_path, capsys):
    """The command's bad value names its option (from the spec's metadata);
    the same fault in a recipe names the recipe field."""
    from tiledsm.cli import main

    biased, gcps = case
    assert main(["orient", *map(str, biased), "--out", str(tmp_path / "o"), "--tile", "32"]) == 2
    assert "tiledsm orient: error: --tile: Input should be greater than or equal to 64" in capsys.readouterr().err
    assert main(["orient", *map(str, biased), "--out", str(tmp_path / "o"), "--geoid", str(gcps)]) == 2
    assert "tiledsm orient: error: --geoid: 'geoid' is the reference DEM's datum: give 'dem' too" in capsys.readouterr().err
    recipe = tmp_path / "orient.yaml"
    recipe.write_text(yaml.safe_dump({"pipeline": "orient", "images": [str(biased[0])],
                                      "orient": {"check_points": str(gcps)}}))
    assert main(["run", str(recipe), "--out", str(tmp_path / "r")]) == 2
    assert "images: one image needs orient.gcps" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (tmp_path / "r").exists()


def test_a_run_of_other_options_is_refused_in_a_finished_folder(case, uninterrupted, tmp_path):
    # a finished run of other options: refused without --overwrite, its
    # products untouched; with --overwrite the new run replaces them
    out = tmp_path / "o"
    shutil.copytree(uninterrupted, out)
    before = {n: (out / n).read_bytes() for n in EXACT}
    line = error_line(run(orient_cmd(case, out, "--model", "shift")), "orient")
    assert f"{out}: --out: holds a run of other inputs or options" in line and "--overwrite" in line
    assert {n: (out / n).read_bytes() for n in EXACT} == before
    ok(run(orient_cmd(case, out, "--model", "shift", "--overwrite")))
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["orient"]["model"] == "shift"


def test_a_run_of_an_older_version_with_the_same_options_is_not_another_run(case, uninterrupted, tmp_path):
    # the folder of a version whose orient: section lacked a field added
    # since (at its default): the same command runs into it, no --overwrite
    out = tmp_path / "o"
    shutil.copytree(uninterrupted, out)
    resolved = yaml.safe_load((out / "recipe.resolved.yaml").read_text())
    del resolved["orient"]["tie_sigma_px"]
    (out / "recipe.resolved.yaml").write_text(yaml.safe_dump(resolved))
    ok(run(orient_cmd(case, out)))
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["orient"]["tie_sigma_px"] == 0.3
    same_products(out, uninterrupted)
