"""``tiledsm compare`` on geographic (EPSG:4326) DEMs, through the command:
the plan describes REF's own grid in degrees instead of demanding a
projected DSM grid (issue 35)."""

import json
import subprocess
import sys

import pytest

from tests.conftest import require_shared


def _compare(ref, other, out, *extra):
    r = subprocess.run([sys.executable, "-m", "tiledsm", "compare", str(ref), str(other), "--out", str(out), *extra],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.mark.realdata
def test_cli_compare_srtm_geographic_finds_the_known_shift(tmp_path):
    d = require_shared("demcompare_dem_pairs", "srtm_shifted")
    dry = _compare(d / "srtm_ref.tif", d / "srtm_blurred_and_shifted.tif", tmp_path / "dry", "--dry-run")
    assert "EPSG:4326, 0.000833333° x 0.000833333° cells, 1000 x 1000 cells" in dry.stdout
    assert not (tmp_path / "dry").exists()
    r = _compare(d / "srtm_ref.tif", d / "srtm_blurred_and_shifted.tif", tmp_path / "o")
    c = json.loads(r.stdout)["coregistration"]
    # demcompare made OTHER as sec[i, j] = ref[i + 5, j + 3]: its Nuth & Kaab finds dx = 3, dy = 5 px
    exp = json.loads((d / "expected_output" / "coregistration_results.json").read_text())["coregistration_results"]
    assert abs(c["dx_px"] - exp["dx"]["total_offset"]) < 0.1
    assert abs(c["dy_px"] - exp["dy"]["total_offset"]) < 0.1
    assert (tmp_path / "o" / "report.html").exists() and (tmp_path / "o" / "dh.tif").exists()


@pytest.mark.realdata
def test_cli_compare_copernicus_geographic_different_resolutions_reports(tmp_path):
    d = require_shared("demcompare_dem_pairs", "grenoble_copernicus")
    _compare(d / "Copernicus_DSM_10_N45_00_E005_00_DEM.tif", d / "Copernicus_blurred_and_shifted.tif", tmp_path / "o")
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    fit = m["coregistration"]["fit_sample"]
    # the shift is undocumented; the fitted one must explain most of the difference (measured: NMAD 57.8 -> 8.4 m)
    assert m["coregistration"]["converged"]
    assert fit["nmad_after"] < 0.2 * fit["nmad_before"]
    assert m["coregistration"]["units"]["dx"] == "degree"
    assert "<html" in (tmp_path / "o" / "report.html").read_text().lower()
