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
