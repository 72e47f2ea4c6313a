"""``tiledsm orient`` end to end on a rendered synthetic pair with injected
biases: products, GDAL reading them back, accuracy at check points, bad
inputs, a blunder GCP reported by id, and ``tiledsm dsm`` on the output."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import rasterio
from orient_cases import write_gcp_files

from tiledsm.cli import main
from tiledsm.geometry import RPC
from tiledsm.io.cameras import find_camera
from simulate import ground_points


@pytest.fixture(scope="module")
def points(scene2):
    info, true, biased, h, root = scene2
    return write_gcp_files(true, [p.name for p in biased], root)


@pytest.fixture(scope="module")
def oriented(scene2, points, tmp_path_factory):
    info, true, biased, h, root = scene2
    out = tmp_path_factory.mktemp("orient_out")
    rc = main(["orient", *map(str, biased), "--gcps", str(points[0]), "--check-points", str(points[1]),
               "--out", str(out), "--tile", "256", "--workers", "1"])
    assert rc == 0
    return out, json.loads((out / "orient.json").read_text())


def test_products_and_accuracy(scene2, oriented):
    info, true, biased, h, root = scene2
    out, doc = oriented
    for v in ("view_0", "view_1"):
        for f in (f"{v}.tif", f"{v}_RPC.TXT"):
            assert (out / f).is_file()
    assert (out / "residuals.png").stat().st_size > 10_000 and (out / "residuals.csv").is_file()
    print(json.dumps({k: doc[k] for k in ("gcp_rms_px", "check_rms_px", "tie_relative_rms_px")}))
    assert doc["check_rms_px"]["before"] > 2.5
    assert doc["check_rms_px"]["after"] < 0.1
    assert doc["tie_relative_rms_px"]["after"] < 0.2 < doc["tie_relative_rms_px"]["before"]
    assert [d["model"] for d in doc["images"]] == ["affine", "affine"]
    # GDAL reads the corrected camera (sidecar first, tags hold the same) and it matches the truth
    lon, lat, hh = ground_points(true[0], (512, 512), (300, 400), 200, seed=5)
    for i, v in enumerate(("view_0", "view_1")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(out / f"{v}.tif") as ds:
                gdal_rpc = RPC.from_gdal(ds.rpcs.to_dict())
                assert ds.read(1).tobytes() == rasterio.open(biased[i]).read(1).tobytes()
        cam, origin = find_camera(out / f"{v}.tif")
        assert cam == gdal_rpc and "sidecar" in origin
        d = np.stack(cam.project(lon, lat, hh), -1) - np.stack(true[i].project(lon, lat, hh), -1)
        assert np.sqrt(np.mean(np.sum(d**2, axis=1))) < 0.1


@pytest.mark.slow
def test_dsm_accepts_corrected_images(scene2, oriented, tmp_path):
    """``tiledsm dsm`` on the corrected copies: the pair needs no relative
    correction any more (< 0.05 px) and the DSM sits on the truth."""
    info, true, biased, h, root = scene2
    out, _ = oriented
    rc = main(["dsm", str(out / "view_0.tif"), str(out / "view_1.tif"), "--out", str(tmp_path / "dsm"),
               "--like", str(info.truth_dsm), "--scheduler", "synchronous", "--no-progress"])
    assert rc == 0
    m = json.loads((tmp_path / "dsm" / "metrics.json").read_text())
    corr = m["report"]["relative_correction_view1_px"]
    assert abs(corr["drow"]) < 0.05 and abs(corr["dcol"]) < 0.05
    with rasterio.open(tmp_path / "dsm" / "dsm.tif") as a, rasterio.open(info.truth_dsm) as b, \
            rasterio.open(info.visible_mask) as v:
        d = (a.read(1) - b.read(1))[v.read(1) == 1]
    med = float(np.nanmedian(d))
    print("DSM - truth median", med)
    assert abs(med) < 0.2


def test_too_few_gcps_for_the_model(scene2, tmp_path, capsys):
    info, true, biased, h, root = scene2
    lines = (root / "gcps.csv").read_text().splitlines()
    two = tmp_path / "two.csv"
    two.write_text("\n".join([lines[0]] + [ln for ln in lines[1:] if ln.split(",")[0] in ("g0", "g1")]) + "\n")
    rc = main(["orient", *map(str, biased), "--gcps", str(two), "--model", "affine", "--out", str(tmp_path / "o"),
               "--no-tie-points"])
    err = capsys.readouterr().err
    assert rc == 2 and "needs at least 3 GCP measurement(s) per image" in err and "view_0.tif has 2" in err


def test_gcp_outside_image_is_refused(scene2, tmp_path, capsys):
    info, true, biased, h, root = scene2
    bad = tmp_path / "bad.csv"
    bad.write_text("id,image,lon,lat,h,row,col\nq,view_1.tif,5.2,44.2,300,600.5,10\n")
    rc = main(["orient", *map(str, biased), "--gcps", str(bad), "--out", str(tmp_path / "o")])
    assert rc == 2 and "point 'q' at row 600.5, col 10 lies outside view_1.tif (512 x 512" in capsys.readouterr().err


def test_blunder_gcp_reported(scene2, points, tmp_path):
    info, true, biased, h, root = scene2
    lines = points[0].read_text().splitlines()
    out = [lines[0]]
    for ln in lines[1:]:
        f = ln.split(",")
        if f[0] == "g2" and f[1] == "view_1.tif":
            f[5] = repr(float(f[5]) + 12.0)  # 12 px blunder
        out.append(",".join(f))
    gcps = tmp_path / "blunder.csv"
    gcps.write_text("\n".join(out) + "\n")
    rc = main(["orient", *map(str, biased), "--gcps", str(gcps), "--check-points", str(points[1]),
               "--out", str(tmp_path / "o"), "--tile", "256", "--workers", "1"])
    doc = json.loads((tmp_path / "o" / "orient.json").read_text())
    assert rc == 0 and doc["rejected_gcps"] == ["g2"]
    assert "g2@view_1.tif" in doc["rejected_measurements"]
    assert doc["check_rms_px"]["after"] < 0.15


def test_dry_run_prints_the_plan_and_writes_nothing(scene2, points, tmp_path, capsys):
    info, true, biased, h, root = scene2
    out = tmp_path / "o"
    rc = main(["orient", *map(str, biased), "--gcps", str(points[0]), "--check-points", str(points[1]),
               "--out", str(out), "--tile", "256", "--dry-run"])
    text = capsys.readouterr().out
    assert rc == 0 and not out.exists()
    assert "plan of tiledsm orient (nothing computed, nothing written)" in text
    assert "tie points: 4 tiles of 256 px over view_0.tif (512 x 512 px), matched in 1 other image(s)" in text
    n_gcp = len({ln.split(",")[0] for ln in points[0].read_text().splitlines()[1:]})
    assert f"--gcps: {points[0]} ({n_gcp} points" in text


def test_interrupted_rerun_leaves_no_report_of_the_earlier_run(scene2, points, oriented, tmp_path, monkeypatch):
    import shutil

    import tiledsm.orient.export as export

    info, true, biased, h, root = scene2
    out = tmp_path / "o"
    shutil.copytree(oriented[0], out)  # the products of a finished run
    copy = export.copy_with_rpc
    calls = {"n": 0}

    def dies_at_the_second_image(*a, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return copy(*a, **kw)

    monkeypatch.setattr(export, "copy_with_rpc", dies_at_the_second_image)
    # other options than the finished run's: --overwrite replaces it
    rc = main(["orient", *map(str, biased), "--gcps", str(points[0]), "--out", str(out), "--no-tie-points",
               "--model", "shift", "--overwrite"])
    assert rc == 130 and calls["n"] == 2
    # no report, and no RPC of the earlier run left to be taken for this one's: only the first image's new ones
    left = sorted(p.name for p in out.iterdir())
    assert left == ["run.log", "view_0.tif", "view_0_RPC.TXT"], left
    assert not (out / "orient.json").exists()


def test_extractor_is_chosen_on_the_command_line(scene2, points, oriented, tmp_path):
    """``--extractor features`` runs the corner + NCC matcher instead of the
    structural default: recorded in orient.json, other tracks, same accuracy."""
    info, true, biased, h, root = scene2
    out = tmp_path / "features"
    rc = main(["orient", *map(str, biased), "--gcps", str(points[0]), "--check-points", str(points[1]),
               "--out", str(out), "--tile", "256", "--workers", "1", "--extractor", "features"])
    assert rc == 0
    doc = json.loads((out / "orient.json").read_text())
    structural = oriented[1]
    assert doc["params"]["extractor"] == "features"
    assert structural["params"]["extractor"] == "structural"
    print("tracks features / structural", doc["n_tracks"], structural["n_tracks"])
    assert doc["n_tracks"] != structural["n_tracks"]
    assert doc["check_rms_px"]["after"] < 0.1 and doc["tie_relative_rms_px"]["after"] < 0.2


def test_a_recipe_sets_the_advanced_parameters(scene2, points, oriented, tmp_path, capsys):
    """``orient.tracks`` and ``orient.adjust`` (recipe only) reach the
    matching and the adjustment through ``tiledsm run``: at most 5 interest
    points per 256-px tile of the reference gives at most 4 x 5 tracks; a
    rejection threshold of half the median residual rejects measurements
    (none are by default) and needs a second round. A bad nested value is
    refused at its field (exit 2, one line, nothing written)."""
    import yaml

    info, true, biased, h, root = scene2
    recipe = {"pipeline": "orient", "images": [str(p) for p in biased],
              "orient": {"gcps": str(points[0]), "tile": 256,
                         "tracks": {"structural": {"points_per_tile": 5}}, "adjust": {"reject_k": 0.5, "min_reject_px": 0.0, "max_rounds": 2}}}
    (tmp_path / "few.yaml").write_text(yaml.safe_dump(recipe))
    assert main(["run", str(tmp_path / "few.yaml"), "--out", str(tmp_path / "few"), "--workers", "1"]) == 0
    doc = json.loads((tmp_path / "few" / "orient.json").read_text())
    print("tracks", doc["n_tracks"], oriented[1]["n_tracks"], "rejected", doc["n_rejected"], oriented[1]["n_rejected"])
    assert 0 < doc["n_tracks"] <= 20 < oriented[1]["n_tracks"]
    assert doc["n_rejected"] > 0 == oriented[1]["n_rejected"] and oriented[1]["adjustment"]["rounds"] == 1
    assert doc["adjustment"]["rounds"] == 2
    assert doc["params"]["tracks"]["structural"]["points_per_tile"] == 5 and doc["params"]["adjust"]["reject_k"] == 0.5

    recipe["orient"]["tracks"]["structural"]["template"] = 14
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(recipe))
    capsys.readouterr()
    assert main(["run", str(tmp_path / "bad.yaml"), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "orient.tracks.structural.template" in err[0] and "odd integer >= 3, got 14" in err[0], err
    assert not (tmp_path / "bad").exists()
