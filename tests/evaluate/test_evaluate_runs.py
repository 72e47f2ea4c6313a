"""``tiledsm evaluate RUN_DIR`` on finished ``deformation`` and ``sr_dsm``
runs, as a user runs it: the runs write no truth scores, the evaluation
writes them, and the refusals.

Oracles (numpy on the small rasters the runs and their scenes wrote, read
with rasterio): for the deformation run (``coreg: none``: the truth ``dh``
is the plain ``post_truth_dsm - truth_dsm``), the ``dh`` error statistics
on the visible ground of both epochs, its completeness and the throw
across the event's trace (medians of the strips, the trace rebuilt from
the event's parameters in ``scene.json``); for the sr_dsm run, every DSM
against the HR-pair DSM and the truth on visible cells, on the cells every
DSM of the table has.
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine

from tiledsm.cli import main

RUN = ["--scheduler", "threads", "--workers", "1", "--no-progress"]
STRIP = (3.0, 20.0)


def _read(path) -> np.ndarray:
    with rasterio.open(path) as src:
        return src.read(1, masked=True).astype(np.float64).filled(np.nan)


def _centres(path) -> tuple[np.ndarray, np.ndarray]:
    with rasterio.open(path) as src:
        t, w, h = src.transform, src.width, src.height
    return t.c + (np.arange(w) + 0.5) * t.a, t.f + (np.arange(h) + 0.5) * t.e


def _stats(err: np.ndarray) -> dict:
    """The statistics of the scores; ``le95``: the smallest ``|err|`` with 95 % of the cells at or
    under it (the histogram's definition, not an interpolation between neighbours of a sparse tail)."""
    med = np.median(err)
    return {"count": err.size, "rmse": np.sqrt(np.mean(err**2)), "mean": np.mean(err), "median": med,
            "nmad": 1.4826 * np.median(np.abs(err - med)),
            "le95": np.percentile(np.abs(err), 95, method="inverted_cdf")}


def _assert_stats(got: dict, err: np.ndarray, what: str) -> None:
    want = _stats(err)
    assert got["count"] == want["count"] > 1000, what
    for k in ("rmse", "mean"):
        assert got[k] == pytest.approx(want[k], rel=1e-6, abs=1e-9), (what, k)
    for k in ("median", "nmad", "le95"):  # histogram reductions: within a bin of range / 2**18
        assert got[k] == pytest.approx(want[k], abs=1e-3), (what, k)


def _evaluate(capsys, *args) -> tuple[int, list[str]]:
    capsys.readouterr()
    rc = main(["evaluate", *map(str, args)])
    return rc, capsys.readouterr().err.strip().splitlines()


def _scores(capsys, run_dir, *args) -> dict:
    """``tiledsm evaluate RUN_DIR ARGS``, which succeeds: its ``evaluation.json``."""
    rc, err = _evaluate(capsys, run_dir, *args)
    assert rc == 0, err
    doc = json.loads((run_dir / "evaluation.json").read_text())
    assert doc["run"] == str(run_dir)
    return doc


def _refused(capsys, run_dir, *args) -> str:
    """The one line of a refused evaluation (exit 2, nothing written)."""
    (run_dir / "evaluation.json").unlink(missing_ok=True)
    rc, err = _evaluate(capsys, run_dir, *args)
    assert rc == 2 and len(err) == 1 and err[0].startswith("tiledsm evaluate: error: "), err
    assert not (run_dir / "evaluation.json").exists()
    return err[0]


def _run(tmp, doc: dict, *options: str):
    """``tiledsm run`` of the recipe ``doc`` into ``tmp/run``: ``(tmp, run folder)``."""
    recipe = tmp / f"{doc['pipeline']}.yaml"
    recipe.write_text(yaml.safe_dump(doc))
    assert main(["run", str(recipe), "--out", str(tmp / "run"), *options]) == 0
    return tmp, tmp / "run"


# --------------------------------------------------------------------------- deformation
@pytest.fixture(scope="module")
def deformation_run(tmp_path_factory):
    """A finished 128 px synthetic event run (no co-registration, with a displacement)."""
    return _run(tmp_path_factory.mktemp("evaluate_deformation"), {
        "pipeline": "deformation",
        "input": {"synth": {"size": 128, "gsd": 0.5, "bh": 0.4, "seed": 2, "event": True, "still": "left"}},
        "grid": {"chunk": 64},
        "compare": {"coreg": "none", "chunk": 64, "strip": list(STRIP)},
        "displacement": {"window": 32, "step": 8},
    }, *RUN)


def _event_distance(scene, x, y) -> np.ndarray:
    """Signed distance to the event's trace (positive: right block), from scene.json."""
    doc = json.loads((scene / "scene.json").read_text())
    p = doc["event"]["params"]
    px, py = p["fault_point"][0] + doc["origin_en"][0], p["fault_point"][1] + doc["origin_en"][1]
    sx, sy = math.sin(math.radians(p["strike_deg"])), math.cos(math.radians(p["strike_deg"]))
    return (x[None, :] - px) * sy - (y[:, None] - py) * sx


def _throw(values: np.ndarray, keep: np.ndarray, d: np.ndarray) -> float:
    band = keep & (np.abs(d) >= STRIP[0]) & (np.abs(d) <= STRIP[1])
    return float(np.median(values[band & (d > 0)]) - np.median(values[band & (d < 0)]))


def test_deformation_run_scored_against_its_scene(deformation_run, capsys):
    _, out = deformation_run
    metrics = json.loads((out / "metrics.json").read_text())
    assert "truth" not in metrics and "truth" not in metrics["displacement"]  # the run grades nothing
    assert not list((out / "scene").glob("true_*.tif"))
    doc = _scores(capsys, out)
    assert doc["pipeline"] == "deformation" and doc["scores"]["truth"] == str(out / "scene")
    got = doc["scores"]["dh"]

    scene = out / "scene"
    dh = _read(out / "compare" / "dh.tif")
    truth = _read(scene / "post_truth_dsm.tif") - _read(scene / "truth_dsm.tif")
    visible = (_read(scene / "visible.tif") > 0.5) & (_read(scene / "post_visible.tif") > 0.999) & np.isfinite(truth)
    ground = visible & (_read(scene / "truth_label.tif") == 0) & (_read(scene / "post_truth_label.tif") == 0)
    ok = np.isfinite(dh)
    err = dh - truth
    assert got["frame"] == "plain truth dh"
    _assert_stats(got["dh_error_visible_ground"], err[ok & ground], "visible ground")
    _assert_stats(got["dh_error_visible"], err[ok & visible], "visible")
    assert got["completeness_visible_ground"] == pytest.approx((ok & ground).sum() / ground.sum(), abs=1e-12)
    d = _event_distance(scene, *_centres(out / "compare" / "dh.tif"))
    throw = got["throw"]
    assert throw["recovered"] == pytest.approx(_throw(dh, ok & ground, d), abs=1e-6)
    assert throw["truth"] == pytest.approx(_throw(truth, ok & ground, d), abs=1e-6)
    assert throw["error"] == pytest.approx(throw["recovered"] - throw["truth"], abs=1e-12)
    assert throw["nominal"] == 2.0 and abs(throw["error"]) < 0.3
    # the displacement/ field scored too: its truth, error maps and profiles under evaluation/
    disp = doc["scores"]["displacement"]
    assert set(disp["components"]) == {"dE", "dN", "dU"} and disp["components"]["dE"]["all"]["count"] > 50
    assert "along_strike" in disp["offsets"]
    for p in doc["scores"]["products"]:
        assert (out / p).stat().st_size > 500, p
    assert "evaluation/profiles.png" in doc["scores"]["products"]


def test_deformation_run_scored_against_a_dh_raster(deformation_run, capsys):
    _, out = deformation_run
    given = out / "scene" / "dh.tif"
    scores = _scores(capsys, out, "--truth", given)["scores"]
    assert scores["truth"] == str(given) and "not_scored" in scores["displacement"]
    dh, truth = _read(out / "compare" / "dh.tif"), _read(given)
    sel = np.isfinite(dh) & np.isfinite(truth)
    _assert_stats(scores["dh"]["dh_error"], (dh - truth)[sel], "dh raster")
    d = _event_distance(out / "scene", *_centres(out / "compare" / "dh.tif"))  # the trace of the run's scene
    assert scores["dh"]["throw"]["truth"] == pytest.approx(_throw(truth, sel, d), abs=1e-6)


def test_real_pairs_run_scored_against_its_recipes_truth_dh(deformation_run, capsys, tmp_path):
    """Given pairs (the event scene's views) with ``input.truth_dh``, ``truth_mask`` and ``fault.trace``
    (two lon/lat points on the event's trace) in the recipe: scored without --truth."""
    from pyproj import Transformer

    _, synth = deformation_run
    scene = synth / "scene"
    doc = json.loads((scene / "scene.json").read_text())
    p = doc["event"]["params"]
    px, py = p["fault_point"][0] + doc["origin_en"][0], p["fault_point"][1] + doc["origin_en"][1]
    sx, sy = math.sin(math.radians(p["strike_deg"])), math.cos(math.radians(p["strike_deg"]))
    to_lonlat = Transformer.from_crs(doc["crs"], "EPSG:4326", always_xy=True)
    trace = [list(to_lonlat.transform(px + k * sx, py + k * sy)) for k in (-40.0, 40.0)]
    _, out = _run(tmp_path, {
        "pipeline": "deformation",
        "input": {"pre": {"images": [str(scene / f"view_{i}.tif") for i in (0, 1)]},
                  "post": {"images": [str(scene / f"post_view_{i}.tif") for i in (0, 1)]},
                  "truth_dh": str(scene / "dh.tif"), "truth_mask": str(scene / "visible.tif")},
        "fault": {"trace": trace},
        "grid": {"like": str(scene / "truth_dsm.tif"), "chunk": 64},
        "compare": {"coreg": "none", "chunk": 64, "strip": list(STRIP)},
    }, *RUN)
    scores = _scores(capsys, out)["scores"]
    assert scores["truth"] == str(scene / "dh.tif") and "displacement" not in scores
    dh, truth = _read(out / "compare" / "dh.tif"), _read(scene / "dh.tif")
    sel = np.isfinite(dh) & np.isfinite(truth) & (_read(scene / "visible.tif") > 0.5)
    _assert_stats(scores["dh"]["dh_error"], (dh - truth)[sel], "truth_dh on truth_mask")
    d = _event_distance(scene, *_centres(out / "compare" / "dh.tif"))
    throw = scores["dh"]["throw"]
    assert throw["recovered"] == pytest.approx(_throw(dh, sel, d), abs=1e-6)
    assert throw["truth"] == pytest.approx(_throw(truth, sel, d), abs=1e-6)


def test_deformation_evaluations_refused(deformation_run, capsys, tmp_path):
    tmp, out = deformation_run
    bare = tmp_path / "no_scene"  # a run folder whose scene is gone, and a recipe without input.truth_dh
    shutil.copytree(out, bare, ignore=lambda d, names: ["scene", "evaluation", "evaluation.json"] if d == str(out) else [])
    line = _refused(capsys, bare)
    assert f"{bare}: the run made no synthetic scene (scene/) and its recipe has no input.truth_dh: give --truth" in line
    line = _refused(capsys, out, "--truth", tmp_path / "nope.tif")
    assert "nope.tif: --truth: no such file or folder" in line
    line = _refused(capsys, out, "--truth", tmp_path)
    assert f"{tmp_path}: --truth: neither a synthetic event scene (scene.json) nor a dh raster" in line
    with rasterio.open(out / "scene" / "dh.tif") as src:
        prof, z = src.profile, src.read(1)
    prof.update(transform=Affine(src.transform.a, 0, src.transform.c + 1e5, 0, src.transform.e, src.transform.f))
    with rasterio.open(tmp_path / "far.tif", "w", **prof) as dst:
        dst.write(z, 1)
    line = _refused(capsys, out, "--truth", tmp_path / "far.tif")
    assert "--truth: " in line and "far.tif" in line and "overlap" in line
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    shutil.copy(out / "recipe.resolved.yaml", unfinished)
    line = _refused(capsys, unfinished)
    assert f"{unfinished}: no compare/dh.zarr: the deformation run did not finish" in line


# --------------------------------------------------------------------------- sr_dsm
@pytest.fixture(scope="module")
def sr_run(tmp_path_factory):
    """A finished 128 px synthetic sr_dsm run: DSM upscale and bicubic SR."""
    return _run(tmp_path_factory.mktemp("evaluate_sr_dsm"), {
        "pipeline": "sr_dsm",
        "input": {"synth": {"size": 128, "gsd": 0.5, "bh": 0.4, "seed": 1}},
        "sr": {"models": ["dsm_upscale", "bicubic"]},
        "grid": {"chunk": 64},
        "output": {"cog": True, "quicklook": False},
    }, "--scheduler", "synchronous", "--no-progress")


def _table(got: dict, common: dict, heights: dict, ref: np.ndarray, mask: np.ndarray, what: str) -> None:
    evaluated = np.isfinite(ref) & mask
    cells = evaluated.copy()
    for h in heights.values():
        cells &= np.isfinite(h)
    assert common["count"] == cells.sum() > 1000 and common["cells"] == evaluated.sum(), what
    for name, h in heights.items():
        row, err = got[name], (h - ref)[cells]
        assert row["count"] == cells.sum(), (what, name)
        assert row["completeness"] == pytest.approx((np.isfinite(h) & evaluated).sum() / evaluated.sum(), abs=1e-12)
        for k, want in (("rmse", np.sqrt(np.mean(err**2))), ("mean", np.mean(err)), ("median", np.median(err)),
                        ("nmad", 1.4826 * np.median(np.abs(err - np.median(err))))):
            assert row[k] == pytest.approx(want, rel=1e-9, abs=1e-9), (what, name, k)


def test_sr_dsm_run_scored_against_its_scene(sr_run, capsys):
    _, out = sr_run
    metrics = json.loads((out / "metrics.json").read_text())
    assert "regions" not in metrics and not {"vs_hr", "vs_truth_visible"} & set(metrics["methods"]["bicubic"])
    assert 20 < metrics["methods"]["bicubic"]["image"]["psnr_db"] < 60  # the run still measures its images
    own = (out / "report.md").read_text()
    assert "**Table 1.**" in own and "**Table 2.**" not in own and "`tiledsm evaluate`" in own
    scores = _scores(capsys, out)["scores"]
    assert scores["truth"] == str(out / "scene") and scores["table_step"] == 1

    hr = _read(out / "hr" / "dsm.tif")
    methods = {"dsm_upscale": _read(out / "dsm_upscale" / "dsm.tif"), "bicubic": _read(out / "bicubic" / "dsm.tif")}
    truth, visible = _read(out / "scene" / "truth_dsm.tif"), _read(out / "scene" / "visible.tif") > 0.5
    rows = scores["dsms"]
    _table({k: rows[k]["vs_hr"] for k in methods}, scores["common"]["vs_hr"], methods, hr,
           np.ones(hr.shape, bool), "vs_hr")
    _table({k: rows[k]["vs_truth_visible"] for k in ("hr", *methods)}, scores["common"]["vs_truth_visible"],
           {"hr": hr, **methods}, truth, visible, "vs_truth_visible")
    # the region of the roofs: visible building cells where every DSM has a height
    roofs = visible & (_read(out / "scene" / "truth_label.tif") == 1) & np.isfinite(truth)
    both = roofs & np.isfinite(hr) & np.isfinite(methods["dsm_upscale"]) & np.isfinite(methods["bicubic"])
    assert scores["regions"]["tables"]["buildings"]["common"]["count"] == both.sum() > 50
    report = (out / "evaluation" / "report.md").read_text()
    for table in ("**Table 1.**", "**Table 2.**", "**Table 3.**", "**Table 4.**"):
        assert table in report
    assert f"Scored on {scores['common']['vs_hr']['count']} common cells" in report
    assert (out / "evaluation" / "blunders.png").stat().st_size > 5_000
    assert sorted(scores["products"]) == ["evaluation/blunders.png", "evaluation/report.md"]


def test_sr_dsm_run_scored_against_a_reference_dsm(sr_run, capsys):
    _, out = sr_run
    given = out / "scene" / "truth_dsm.tif"
    scores = _scores(capsys, out, "--truth", given)["scores"]
    assert scores["truth"] == str(given) and "regions" not in scores
    hr, truth = _read(out / "hr" / "dsm.tif"), _read(given)
    methods = {"dsm_upscale": _read(out / "dsm_upscale" / "dsm.tif"), "bicubic": _read(out / "bicubic" / "dsm.tif")}
    _table({k: scores["dsms"][k]["vs_reference"] for k in ("hr", *methods)}, scores["common"]["vs_reference"],
           {"hr": hr, **methods}, truth, np.ones(hr.shape, bool), "vs_reference")
    assert "the given reference DSM `truth_dsm.tif`" in (out / "evaluation" / "report.md").read_text()


def test_sr_dsm_evaluations_refused(sr_run, deformation_run, capsys, tmp_path):
    _, out = sr_run
    line = _refused(capsys, out, "--truth", tmp_path / "nothing")
    assert "nothing: --truth: no such file or folder" in line
    line = _refused(capsys, out, "--truth", tmp_path)
    assert f"{tmp_path}: --truth: neither a reference DSM nor a synthetic scene folder (no scene.json)" in line
    unfinished = tmp_path / "unfinished"
    shutil.copytree(out, unfinished, ignore=lambda d, names: ["bicubic", "evaluation", "evaluation.json"]
                    if d == str(out) else [])
    line = _refused(capsys, unfinished)
    assert f"{unfinished}: no bicubic/dsm.tif: the sr_dsm run did not finish" in line
    # the sr run's scene has no event: it is no deformation truth
    _, deformation = deformation_run
    line = _refused(capsys, deformation, "--truth", out / "scene")
    assert f"{out / 'scene'}: --truth: a synthetic scene without an event" in line
