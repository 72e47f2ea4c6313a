"""``tiledsm evaluate RUN_DIR [--truth PATH]`` as a user runs it: a finished
``tiledsm displace`` run scored against true displacement rasters, a
``tiledsm dsm`` run against its synthetic scene, and the refusals.

Oracles: the displace truth is analytic (the right block of a straight
north-south trace moved by ``SHIFT``; POST samples PRE's continuous image
at ``q - d(q)``, ``displace_cases``), averaged over each field cell's
step x step ortho pixels here, in numpy, from the field's own
coordinates; the DSM scores are numpy statistics of the whole small
``dsm.tif - truth_dsm.tif`` read with rasterio.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import xarray as xr
from affine import Affine
from scipy import ndimage

from tests.displace.displace_cases import Trace, post_on_grid, spline_source, write_tif
from tiledsm.cli import main

RES, SIDE = 0.5, 192
X0, Y0 = 500000.0, 4000000.0
CRS = "EPSG:32631"
#: a north-south trace between ortho pixel edges (and field cell edges): no field cell straddles it
TRACE_X = X0 + 48.1
#: the moved (east) block, metres east and north
SHIFT = (1.3, -0.9)
STEP, WINDOW = 8, 32


def _lonlat_polygon(xmin, ymin, xmax, ymax) -> dict:
    from pyproj import Transformer

    t = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    ring = [t.transform(x, y) for x, y in ((xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax), (xmin, ymin))]
    return {"type": "Polygon", "coordinates": [[list(p) for p in ring]]}


def _truth_folder(folder, x0: float) -> None:
    """True dE.tif, dN.tif on PRE's grid placed at ``x0``: SHIFT east of the trace, 0 west."""
    folder.mkdir()
    t = Affine(RES, 0, x0, 0, -RES, Y0)
    xc = x0 + (np.arange(SIDE) + 0.5) * RES
    moved = np.broadcast_to(xc > TRACE_X, (SIDE, SIDE))
    write_tif(folder / "dE.tif", np.where(moved, SHIFT[0], 0.0), t, CRS)
    write_tif(folder / "dN.tif", np.where(moved, SHIFT[1], 0.0), t, CRS)


@pytest.fixture(scope="module")
def displaced(tmp_path_factory):
    """A finished ``tiledsm displace`` run (east block moved, stable mask on it) and its truth."""
    tmp = tmp_path_factory.mktemp("evaluate_displace")
    rng = np.random.default_rng(3)
    img = ndimage.gaussian_filter(rng.normal(size=(SIDE, SIDE)), 1.5) * 200 + 1000
    t = Affine(RES, 0, X0, 0, -RES, Y0)
    trace = Trace((TRACE_X, Y0 - 48.0), (0.0, 1.0), SHIFT)
    post = post_on_grid(spline_source(img), t, CRS, trace, t, img.shape, CRS)
    pre_p, post_p = write_tif(tmp / "pre.tif", img, t, CRS), write_tif(tmp / "post.tif", post, t, CRS)
    (tmp / "moving.geojson").write_text(json.dumps(_lonlat_polygon(TRACE_X, Y0 - 200, X0 + 200, Y0 + 50)))
    _truth_folder(tmp / "truth", X0)
    _truth_folder(tmp / "truth_far", X0 + 5000)
    out = tmp / "run"
    rc = main(["displace", pre_p, post_p, "--out", str(out), "--window", str(WINDOW), "--step", str(STEP),
               "--stable-mask", str(tmp / "moving.geojson"), "--no-progress"])
    assert rc == 0
    return tmp, out


def _stats(err: np.ndarray) -> dict:
    med = np.median(err)
    return {"count": err.size, "rmse": np.sqrt(np.mean(err**2)), "mean": np.mean(err), "median": med,
            "nmad": 1.4826 * np.median(np.abs(err - med)), "le95": np.percentile(np.abs(err), 95)}


def test_displace_run_scored_against_true_rasters(displaced, capsys):
    tmp, out = displaced
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(tmp / "truth")]) == 0
    printed = json.loads(capsys.readouterr().out)
    doc = json.loads((out / "evaluation.json").read_text())
    assert printed["pipeline"] == doc["pipeline"] == "displace"
    scores = doc["scores"]

    # the oracle: the analytic truth averaged over each field cell's 8 x 8 ortho pixels (columns only matter)
    field = xr.open_zarr(out / "displacement.zarr", consolidated=False)
    x = field.x.values
    dx = x[1] - x[0]
    assert dx == pytest.approx(STEP * RES)
    sub = x[:, None] - dx / 2 + (np.arange(STEP) + 0.5) * dx / STEP
    moved_share = (sub > TRACE_X).mean(axis=1)
    assert set(np.unique(moved_share)) <= {0.0, 1.0}  # no cell straddles the trace
    stable = np.broadcast_to(x < TRACE_X, (len(field.y), len(x)))  # outside the moving polygon
    for n, shift in (("dE", SHIFT[0]), ("dN", SHIFT[1])):
        truth = np.broadcast_to(moved_share * float(np.float32(shift)), stable.shape)  # as the truth file holds it
        assert np.median(truth[stable]) == 0.0  # the stable frame is the truth's own
        v = np.asarray(field[n].values, np.float64)
        sigma = np.asarray(field[f"sigma_{n}"].values, np.float64)
        err = v - truth
        ok = np.isfinite(err)
        got = scores["components"][n]
        for part, sel in (("all", ok), ("stable", ok & stable), ("moving", ok & ~stable)):
            want = _stats(err[sel])
            assert got[part]["count"] == want["count"] > 100
            for k in ("rmse", "mean", "median", "nmad", "le95"):
                assert got[part][k] == pytest.approx(want[k], rel=1e-9, abs=1e-12), (n, part, k)
        okc = ok & np.isfinite(sigma)
        assert got["within_2_sigma"] == pytest.approx(np.mean(np.abs(err[okc]) <= 2 * sigma[okc]), abs=1e-12)
        assert got["all"]["nmad_px"] == pytest.approx(got["all"]["nmad"] / RES)
        # and the field is right: the moved block's motion recovered to a few hundredths of a pixel
        assert got["moving"]["median"] == pytest.approx(0, abs=0.02 * RES)
    assert scores["frame"] == {"dE": 0.0, "dN": 0.0}
    with rasterio.open(out / "evaluation" / "true_dE.tif") as src, rasterio.open(out / "dE.tif") as run:
        assert src.transform == run.transform and src.shape == run.shape
        assert np.array_equal(src.read(1), np.broadcast_to(moved_share * SHIFT[0], src.shape).astype(np.float32))
    for n in ("dE", "dN"):
        assert (out / "evaluation" / f"error_{n}.png").stat().st_size > 1000
    assert sorted(scores["products"]) == ["evaluation/error_dE.png", "evaluation/error_dN.png",
                                          "evaluation/true_dE.tif", "evaluation/true_dN.tif"]


@pytest.mark.parametrize("args, needle", [
    (lambda t, o: [str(t / "nope")], "nope: RUN_DIR: no such folder"),
    (lambda t, o: [str(t / "truth")], "truth: RUN_DIR: not a finished tiledsm run (no recipe.resolved.yaml)"),
    (lambda t, o: [str(o)], "the run made no synthetic scene: give --truth"),
    (lambda t, o: [str(o), "--truth", str(t / "nothing")], "nothing: --truth: no such file or folder"),
    (lambda t, o: [str(o), "--truth", str(t)], "--truth: neither a synthetic event scene (scene.json) nor a folder "
                                               "with the true dE.tif and dN.tif"),
    (lambda t, o: [str(o), "--truth", str(t / "truth_far")], "truth_far: --truth: covers no cell of the run's "
                                                             "displacement field"),
])
def test_bad_evaluations_exit_2_with_one_line_and_write_nothing(displaced, capsys, args, needle):
    tmp, out = displaced
    (out / "evaluation.json").unlink(missing_ok=True)
    capsys.readouterr()
    rc = main(["evaluate", *args(tmp, out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("tiledsm evaluate: error: ") and needle in err[0], err
    assert not (out / "evaluation.json").exists()


@pytest.fixture(scope="module")
def dsm_run(tmp_path_factory):
    """A finished ``tiledsm dsm`` run of a tiny synthetic pair, on its truth's grid."""
    from tiledsm.synth import make_scene

    tmp = tmp_path_factory.mktemp("evaluate_dsm")
    s = make_scene(tmp / "scene", size=160, gsd=0.5, bh=0.4, seed=11, views=2)
    out = tmp / "run"
    rc = main(["dsm", str(s.views[0]), str(s.views[1]), "--out", str(out), "--like", str(s.truth_dsm),
               "--chunk", "64", "--no-progress", "--workers", "1", "--scheduler", "threads"])
    assert rc == 0
    return s, out


def test_dsm_run_scored_against_its_synthetic_scene(dsm_run, capsys):
    s, out = dsm_run
    assert main(["evaluate", str(out), "--truth", str(s.out_dir)]) == 0
    scores = json.loads((out / "evaluation.json").read_text())["scores"]
    with rasterio.open(out / "dsm.tif") as a, rasterio.open(s.truth_dsm) as b, rasterio.open(s.visible_mask) as m:
        assert a.transform == b.transform and a.shape == b.shape
        dsm, truth, visible = a.read(1, masked=True).filled(np.nan), b.read(1), m.read(1) > 0
    diff = dsm.astype(np.float64) - truth
    for key, sel in (("vs_reference", np.isfinite(diff)), ("vs_reference_visible", np.isfinite(diff) & visible)):
        want, got = _stats(diff[sel]), scores[key]
        assert got["count"] == want["count"] > 1000
        assert got["completeness"] == pytest.approx(sel.sum() / (np.isfinite(truth) & (visible if key.endswith(
            "visible") else True)).sum())
        for k in ("mean", "rmse"):
            assert got[k] == pytest.approx(want[k], rel=1e-5, abs=1e-6), (key, k)
        for k in ("median", "nmad"):  # histogram reductions: within a bin
            assert got[k] == pytest.approx(want[k], abs=2e-3), (key, k)
    assert (out / "evaluation" / "dsm_error.png").stat().st_size > 1000


def test_dsm_truth_that_does_not_fit_is_refused(dsm_run, tmp_path, capsys):
    s, out = dsm_run
    with rasterio.open(s.truth_dsm) as src:
        prof, z = src.profile, src.read(1)
    prof.update(transform=Affine(src.transform.a, 0, src.transform.c + 1e5, 0, src.transform.e, src.transform.f))
    with rasterio.open(tmp_path / "far.tif", "w", **prof) as dst:
        dst.write(z, 1)
    (out / "evaluation.json").unlink(missing_ok=True)
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(tmp_path / "far.tif")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--truth: DSMs do not overlap" in err[0] and "far.tif" in err[0], err
    assert not (out / "evaluation.json").exists()


def test_a_scene_without_an_event_is_no_displacement_truth(displaced, dsm_run, capsys):
    s, _ = dsm_run
    _, out = displaced
    (out / "evaluation.json").unlink(missing_ok=True)
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(s.out_dir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--truth: a synthetic scene without an event" in err[0] and str(s.out_dir) in err[0]
    assert not (out / "evaluation.json").exists()


def test_a_pipeline_without_a_truth_is_refused(tmp_path, capsys):
    (tmp_path / "recipe.resolved.yaml").write_text("pipeline: train_sr\n")
    assert main(["evaluate", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{tmp_path}: RUN_DIR: a train_sr run has no truth to be scored against" in err[0], err
    assert not (tmp_path / "evaluation.json").exists()
