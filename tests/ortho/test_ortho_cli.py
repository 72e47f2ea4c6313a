"""``tiledsm ortho``: products on a synthetic scene, errors, and the real
Pleiades pair on tiledsm's own DSM (the two orthos agree on the ground)."""

import json

import numpy as np
import pytest
import rasterio
from skimage.registration import phase_cross_correlation

from tests.conftest import require_shared
from tiledsm.cli import main
from tiledsm.io import open_product


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(1), ds.crs


def test_cli_writes_products(ortho_scene, tmp_path, capsys):
    out = tmp_path / "o"
    rc = main(["ortho", str(ortho_scene.views[0]), "--dsm", str(ortho_scene.truth_dsm), "--out", str(out),
               "--kernel", "cr", "--resolution", "0.25", "--chunk", "128", "--scheduler", "synchronous", "--no-progress"])
    assert rc == 0
    z = open_product(out / "ortho.zarr")
    tif, crs = _read(out / "ortho.tif")
    assert z.shape == (512, 512) and crs == ortho_scene.grid.crs
    np.testing.assert_array_equal(tif, z.values)
    rep = json.loads((out / "ortho.json").read_text())
    assert rep["attrs"]["kernel"] == "CR" and rep["attrs"]["factor"] == 2 and rep["resolution_m"] == 0.25
    assert 0.85 < rep["valid_share"] < 0.99  # hidden cells are NaN
    assert (out / "ortho.png").stat().st_size > 10_000
    assert "512 x 512 cells of 0.25 m" in capsys.readouterr().out


def test_cli_errors(ortho_scene, tmp_path, capsys):
    base = ["ortho", str(ortho_scene.views[0]), "--dsm", str(ortho_scene.truth_dsm), "--out", str(tmp_path / "x"),
            "--scheduler", "synchronous"]
    assert main(base + ["--kernel", "bicubic"]) == 2
    assert "--kernel: unknown interpolation kernel 'bicubic'" in capsys.readouterr().err
    assert main(base + ["--resolution", "0.3"]) == 2
    assert "--resolution: 0.3 m does not divide the DSM's 0.5 m cells" in capsys.readouterr().err
    assert main(base + ["--crs", "EPSG:4326"]) == 2
    assert "the ortho is asked in EPSG:4326 but the DSM is in" in capsys.readouterr().err
    assert main(base + ["--bounds", "0", "0", "10", "10"]) == 2
    assert "is not covered by the DSM" in capsys.readouterr().err
    assert not (tmp_path / "x" / "ortho.tif").exists()


KNOWN = "known: ['bl', 'cr', 'cs', 'nn']"


@pytest.mark.parametrize("command, extra, line", [
    ("ortho", ["--dsm", "d.tif", "--kernel", "zz"],
     f"tiledsm ortho: error: --kernel: unknown interpolation kernel 'zz'; {KNOWN}"),
    ("ortho", ["--dsm", "d.tif", "--occlusion-tolerance", "-1"],
     "tiledsm ortho: error: --occlusion-tolerance: Input should be greater than or equal to 0"),
    # an image orthorectified before the correlation: the same kernel field
    ("displace", ["b.tif", "--dsm-pre", "d.tif", "--kernel", "zz"],
     f"tiledsm displace: error: --kernel: unknown interpolation kernel 'zz'; {KNOWN}"),
])
def test_a_bad_parameter_is_one_line_naming_its_option(tmp_path, capsys, command, extra, line):
    """The parameters' own checks (the spec's field validators) refuse a
    bad value before any file is opened: exit 2, one line, the option."""
    out = tmp_path / "o"
    assert main([command, str(tmp_path / "a.tif"), *extra, "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [line]
    assert not out.exists()


@pytest.mark.parametrize("pipeline, section, fields, located", [
    ("ortho", "ortho", {"step": 0}, "ortho.step: Input should be greater than 0"),
    ("ortho", "ortho", {"kernel": "zz"}, f"ortho.kernel: Value error, unknown interpolation kernel 'zz'; {KNOWN}"),
    ("displace", "input", {"kernel": "zz"}, f"input.kernel: Value error, unknown interpolation kernel 'zz'; {KNOWN}"),
])
def test_a_bad_parameter_in_a_recipe_names_its_field(tmp_path, capsys, pipeline, section, fields, located):
    """``tiledsm run`` of a recipe with a bad ortho parameter (``step`` has
    no option: recipe only) names the recipe field."""
    import yaml

    inputs = {"ortho": {"image": "a.tif", "dsm": "d.tif"}, "displace": {"pre": "a.tif", "post": "b.tif"}}[pipeline]
    recipe = {"pipeline": pipeline, "input": inputs}
    recipe[section] = {**recipe.get(section, {}), **fields}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["run", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tiledsm run: error: ") and located in err[0], err
    assert "--kernel" not in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
@pytest.mark.realdata
def test_s2p_pair_orthos_agree_on_tiledsm_dsm(tmp_path):
    pair = require_shared("s2p_pair", "input_pair")
    imgs = [str(pair / "img_01.tif"), str(pair / "img_02.tif")]
    # a 200 m x 200 m DSM in the middle of the overlap (tiledsm's own matching)
    bounds = ["359830", "7651630", "360030", "7651830"]
    assert main(["dsm", *imgs, "--out", str(tmp_path / "dsm"), "--bounds", *bounds, "--resolution", "0.5", "--crs", "EPSG:32740",
                 "--chunk", "256", "--scheduler", "synchronous", "--no-progress"]) == 0
    orthos = []
    for k, img in enumerate(imgs):
        out = tmp_path / f"o{k}"
        assert main(["ortho", img, "--dsm", str(tmp_path / "dsm" / "dsm.zarr"), "--out", str(out), "--kernel", "cs",
                     "--scheduler", "synchronous", "--no-progress"]) == 0
        assert (out / "ortho.png").is_file()
        orthos.append(_read(out / "ortho.tif")[0])
    a, b = orthos
    shifts = []
    for i in range(0, 400 - 99, 100):
        for j in range(0, 400 - 99, 100):
            ta, tb = a[i:i + 100, j:j + 100], b[i:i + 100, j:j + 100]
            ok = np.isfinite(ta) & np.isfinite(tb)
            if ok.mean() < 0.85:  # stable, matched ground only
                continue
            s, _, _ = phase_cross_correlation(np.where(ok, ta, np.nanmean(ta)), np.where(ok, tb, np.nanmean(tb)),
                                              upsample_factor=100)
            shifts.append(np.hypot(*s))
    print("tile shifts (px):", np.round(shifts, 3))
    assert len(shifts) >= 8
    # measured: every tile within 0.05 px (the raw RPCs, without the DSM's relative correction: up to 0.35 px)
    assert max(shifts) <= 0.06  # the issue asks <= 0.2 px


def test_dry_run_prints_the_plan_and_writes_nothing(ortho_scene, tmp_path, capsys):
    out = tmp_path / "o"
    rc = main(["ortho", str(ortho_scene.views[0]), "--dsm", str(ortho_scene.truth_dsm), "--out", str(out),
               "--resolution", "0.25", "--chunk", "128", "--dry-run"])
    text = capsys.readouterr().out
    assert rc == 0 and not out.exists()
    assert "plan of tiledsm ortho (nothing computed, nothing written)" in text
    assert "0.25 m cells (DSM cell / 2), 512 x 512 cells, chunks of 128: 4 x 4 = 16" in text
    assert "tasks" in text and "warnings  none" in text


def test_dsm_mostly_outside_the_image_warns(ortho_scene, tmp_path, capsys):
    # the truth DSM in the middle of a grid three times as wide: the image sees ~1/9 of it
    with rasterio.open(ortho_scene.truth_dsm) as src:
        h, prof = src.read(1), src.profile
    big = np.full((3 * h.shape[0], 3 * h.shape[1]), float(np.nanmedian(h)), np.float32)
    big[h.shape[0]:2 * h.shape[0], h.shape[1]:2 * h.shape[1]] = h
    t = prof["transform"]
    prof.update(width=big.shape[1], height=big.shape[0],
                transform=rasterio.Affine(t.a, 0, t.c - h.shape[1] * t.a, 0, t.e, t.f - h.shape[0] * t.e))
    with rasterio.open(tmp_path / "big.tif", "w", **prof) as dst:
        dst.write(big, 1)
    rc = main(["ortho", str(ortho_scene.views[0]), "--dsm", str(tmp_path / "big.tif"), "--out", str(tmp_path / "o"),
               "--dry-run"])
    cap = capsys.readouterr()
    assert rc == 0
    assert "IMAGE sees only" in cap.err and "of the ortho grid" in cap.err
    share = float(cap.err.split("sees only ")[1].split("%")[0]) / 100
    assert 0.08 <= share <= 0.20  # 1/9 of the area, sampled on a 17 x 17 lattice


def test_interrupted_rerun_leaves_no_report_of_the_earlier_run(ortho_scene, tmp_path, monkeypatch, capsys):
    """Other parameters into a finished folder are refused (exit 2, the
    products left alone) until --overwrite; an --overwrite run interrupted
    midway leaves no report, export or metrics of either run, and the same
    command without --overwrite then resumes its chunks."""
    import tiledsm.ortho.rectify as rectify

    out = tmp_path / "o"
    base = ["ortho", str(ortho_scene.views[0]), "--dsm", str(ortho_scene.truth_dsm), "--out", str(out),
            "--chunk", "64", "--scheduler", "synchronous", "--no-progress"]
    assert main(base + ["--kernel", "bl"]) == 0
    report = (out / "ortho.json").read_bytes()
    capsys.readouterr()
    assert main(base + ["--kernel", "cr"]) == 2
    err = capsys.readouterr().err
    assert "ortho.zarr: the result stored here" in err and "params.kernel: BL -> CR" in err and "--overwrite" in err
    assert (out / "ortho.json").read_bytes() == report
    calls = {"n": 0}
    block = rectify._ortho_block

    def dies_midway(*a, block_id=None, **kw):  # dask passes block_id to functions that name it
        calls["n"] += 1
        if calls["n"] == 5:  # of 16 chunks
            raise KeyboardInterrupt
        return block(*a, block_id=block_id, **kw)

    monkeypatch.setattr(rectify, "_ortho_block", dies_midway)
    assert main(base + ["--kernel", "cr", "--overwrite"]) == 130  # what Ctrl-C gives
    assert calls["n"] == 5
    # nothing describes the earlier store, nor the new one
    assert not any((out / n).exists() for n in ("ortho.json", "ortho.tif", "ortho.png", "ortho.zarr", "metrics.json",
                                                "recipe.resolved.yaml", ".tiledsm.lock"))
    assert (out / "ortho.zarr.partial").is_dir()
    monkeypatch.undo()
    capsys.readouterr()
    assert main(base + ["--kernel", "cr"]) == 0
    chunks = json.loads((out / "metrics.json").read_text())["timings"]["chunks"]
    assert chunks["chunks_total"] == 16 and 1 <= chunks["chunks_reused"] <= 4
    assert f"reused {chunks['chunks_reused']} of 16 chunks" in capsys.readouterr().out
    assert json.loads((out / "ortho.json").read_text())["attrs"]["kernel"] == "CR"
