"""The comparison stage end to end: demcompare's SRTM pair, a synthetic earthquake, bad inputs, CLI."""

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio

from tests.conftest import require_shared
from tiledsm.compare import CompareOutput, CompareSpec, NoStableTerrainError, compare_dsms
from tiledsm.errors import InputFileError, NoOverlapError

PRODUCTS = {"dh.zarr", "dh.tif", "dh.png", "dh_hist.png", "dh_slope_classes.png", "metrics.json", "report.html"}

# demcompare expected_output/stats_results_slope_classes.csv (NMAD, RMSE after co-registration)
DEMCOMPARE_SLOPE = {
    "[0%;5%[": (1.4826, 2.37626),
    "[5%;10%[": (2.9652, 3.55114),
    "[10%;25%[": (2.9652, 4.53896),
    "[25%;45%[": (5.9304, 5.72303),
    "[45%;inf[": (5.9304, 6.05356),
}


@pytest.fixture(scope="module")
def srtm_run(tmp_path_factory):
    d = require_shared("demcompare_dem_pairs", "srtm_shifted")
    out = tmp_path_factory.mktemp("srtm")
    res = compare_dsms(d / "srtm_ref.tif", d / "srtm_blurred_and_shifted.tif", out, CompareSpec(chunk=256))
    return d, res


@pytest.mark.realdata
def test_srtm_shift_matches_demcompare(srtm_run):
    d, res = srtm_run
    exp = json.loads((d / "expected_output" / "coregistration_results.json").read_text())["coregistration_results"]
    c = res.metrics["coregistration"]
    # sec[i, j] = ref[i + 5, j + 3]: the other DSM must move +3 columns, +5 rows (demcompare: dx=3, dy=5 px)
    assert abs(c["dx_px"] - exp["dx"]["total_offset"]) < 0.1 and abs(c["dy_px"] - exp["dy"]["total_offset"]) < 0.1
    # geographic CRS: degrees (dy < 0: the content moves south) and metres
    assert c["dx"] == pytest.approx(exp["dx"]["total_bias_value"], abs=1e-4)
    assert c["dy"] == pytest.approx(-exp["dy"]["total_bias_value"], abs=1e-4)
    assert c["dx_m"] == pytest.approx(3 * 71.1, rel=0.01) and c["dy_m"] == pytest.approx(-5 * 92.5, rel=0.01)
    # demcompare: dz = mean(ref - sec) = -0.01765 m on int16 heights; ours (median of stable dh) within 2 cm
    assert abs(c["dz"] - exp["dz"]["total_bias_value"]) < 0.02
    assert c["fit_sample"]["nmad_after"] < 0.1 * c["fit_sample"]["nmad_before"]
    assert set(p.name for p in res.out_dir.iterdir()) == PRODUCTS


@pytest.mark.realdata
def test_srtm_slope_class_statistics_match_demcompare(srtm_run):
    _, res = srtm_run
    classes = res.metrics["slope_classes"]
    assert list(classes) == list(DEMCOMPARE_SLOPE)
    for label, (nmad, rmse) in DEMCOMPARE_SLOPE.items():
        # NMAD within 3 %; RMSE within 12 % (demcompare clips outliers at about +-16 m, we at 5 NMAD ~ 22 m)
        assert classes[label]["nmad"] == pytest.approx(nmad, rel=0.03), label
        assert classes[label]["rmse"] == pytest.approx(rmse, rel=0.12), label
        assert abs(classes[label]["median"]) < 0.05


@pytest.mark.realdata
def test_srtm_products_are_consistent(srtm_run):
    d, res = srtm_run
    from tiledsm.io import open_product

    ds = open_product(res.out_dir / "dh.zarr")
    dh = ds["dh"].values
    with rasterio.open(res.out_dir / "dh.tif") as cog:
        assert cog.crs.to_epsg() == 4326 and cog.overviews(1)
        assert np.array_equal(np.isnan(cog.read(1)), np.isnan(dh))
    with rasterio.open(d / "srtm_ref.tif") as r, rasterio.open(d / "srtm_blurred_and_shifted.tif") as o:
        ref = r.read(1).astype(float)[: o.height, : o.width]
        oth = o.read(1).astype(float)
    # independent check of the product: integer-shift the other DSM by (5, 3) and difference
    expect = np.full_like(oth, np.nan)
    expect[5:, 3:] = oth[:-5, :-3] - ref[5:, 3:]
    ok = np.isfinite(dh) & np.isfinite(expect)
    assert ok.mean() > 0.98
    assert np.median(np.abs(dh[ok] - expect[ok])) < 0.05
    all_stats = res.metrics["statistics"]["all"]
    exact = np.nanmedian(dh)
    assert abs(all_stats["median"] - exact) <= res.metrics["histogram"]["median_nmad_resolution_m"]
    assert all_stats["count"] == int(np.isfinite(dh).sum())
    html = (res.out_dir / "report.html").read_text()
    assert html.count("data:image/png;base64,") == 3 and "nuth_kaab" in html


# ---------------------------------------------------------------------------- synthetic event
FAULT_COL, ROWS = 200, (100, 400)
THROW, SLIP = 2.0, 3.0  # m: east block up 2 m, moved 3 m north
UPLIFT, SIGMA, UC = 1.5, 400.0, (430, 90)  # Gaussian uplift (m, m, (row, col))
MISREG = (1.6, 2.3)  # other[i, j] = post(i + 1.6, j + 2.3)


def _event(synth, shape=(512, 512)):
    x, y = synth.centres(shape)
    pre = synth.terrain(x, y)
    r = (synth.Y0 - y) / synth.RES - 0.5
    c = (x - synth.X0) / synth.RES - 0.5

    def post_at(xx, yy):
        rr = (synth.Y0 - yy) / synth.RES - 0.5
        cc = (xx - synth.X0) / synth.RES - 0.5
        block = (cc >= FAULT_COL - 0.5) & (rr >= ROWS[0] - 0.5) & (rr < ROWS[1] - 0.5)
        uy = np.where(block, SLIP, 0.0)
        uz = np.where(block, THROW, 0.0) + UPLIFT * np.exp(-((rr - UC[0]) ** 2 + (cc - UC[1]) ** 2) * synth.RES**2 / (2 * SIGMA**2))
        return synth.terrain(xx, yy - uy) + uz

    truth = post_at(x, y) - pre
    xo, yo = synth.centres(shape, *MISREG)
    other = post_at(xo, yo) + np.random.default_rng(3).normal(0, 0.05, shape)
    return pre, other, truth, r, c


def _rupture_geojson(synth, path):
    from pyproj import Transformer

    tr = Transformer.from_crs(synth.CRS, "EPSG:4326", always_xy=True)

    def ring(r0, r1, c0, c1):
        pts = [(c0, r0), (c1, r0), (c1, r1), (c0, r1), (c0, r0)]
        return [list(tr.transform(synth.X0 + synth.RES * cc, synth.Y0 - synth.RES * rr)) for cc, rr in pts]

    k = 3 * SIGMA / synth.RES
    feats = [
        {"type": "Feature", "properties": {"name": "rupture block"}, "geometry": {"type": "Polygon", "coordinates": [ring(ROWS[0] - 5, ROWS[1] + 5, FAULT_COL - 5, 512)]}},
        {"type": "Feature", "properties": {"name": "uplift"}, "geometry": {"type": "Polygon", "coordinates": [ring(UC[0] - k, UC[0] + k, UC[1] - k, UC[1] + k)]}},
    ]
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    return path


def test_synthetic_event_recovers_misregistration_and_vertical_field(synth, tmp_path):
    pre, other, truth, r, c = _event(synth)
    gj = _rupture_geojson(synth, tmp_path / "rupture.geojson")
    res = compare_dsms(synth.to_dataarray(pre, "pre"), synth.to_dataarray(other, "post"), tmp_path / "out",
                       CompareSpec(stable_mask=str(gj), chunk=128), CompareOutput(quicklook=False, cog=False))
    co = res.coregistration
    assert co.dy_px == pytest.approx(MISREG[0], abs=0.1) and co.dx_px == pytest.approx(MISREG[1], abs=0.1)
    from tiledsm.io import open_product

    dh = open_product(res.out_dir / "dh.zarr")["dh"].values.astype(float)
    ok = np.isfinite(dh)
    assert ok.mean() > 0.97
    rmse = float(np.sqrt(np.mean((dh[ok] - truth[ok]) ** 2)))
    assert rmse <= 0.5
    # throw across the fault: median dh 3-15 cells east minus 3-15 cells west, along the rupture
    rows = slice(ROWS[0] + 10, ROWS[1] - 10)
    east = np.nanmedian(dh[rows, FAULT_COL + 3 : FAULT_COL + 15])
    west = np.nanmedian(dh[rows, FAULT_COL - 15 : FAULT_COL - 3])
    assert east - west == pytest.approx(THROW, abs=0.3)
    st = res.metrics["statistics"]
    assert st["stable"]["nmad"] < 0.15 and abs(st["stable"]["median"]) < 0.05
    print(f"event: shift ({co.dx_px:.3f}, {co.dy_px:.3f}) px, rmse {rmse:.3f} m, throw {east - west:.3f} m")


def test_synthetic_event_without_polygon_absorbs_signal(synth, tmp_path):
    """Without the rupture zone excluded the fit is pulled by the signal (why the polygon exists)."""
    pre, other, truth, r, c = _event(synth)
    from tiledsm.compare import align_dsms, fit_coregistration

    pair = align_dsms(synth.to_dataarray(pre, "pre"), synth.to_dataarray(other, "post"), chunks=256)
    masked = fit_coregistration(pair, CompareSpec(), [])
    err = np.hypot(masked.dx_px - MISREG[1], masked.dy_px - MISREG[0])
    gj = _rupture_geojson(synth, tmp_path / "r.geojson")
    from tiledsm.compare.stable import read_polygons

    good = fit_coregistration(pair, CompareSpec(stable_mask=str(gj)), read_polygons(gj, pair.crs))
    err_good = np.hypot(good.dx_px - MISREG[1], good.dy_px - MISREG[0])
    assert err_good < 0.05 and err_good < err


# ---------------------------------------------------------------------------- bad inputs
def test_all_nan_input_is_a_clear_error_and_writes_nothing(synth, tmp_path):
    z = synth.terrain(*synth.centres((64, 64)))
    a = synth.write_tif(tmp_path / "a.tif", z)
    b = synth.write_tif(tmp_path / "b.tif", np.full(z.shape, -9999.0), nodata=-9999)
    out = tmp_path / "out"
    with pytest.raises(InputFileError, match=r"b\.tif: no valid height"):
        compare_dsms(a, b, out)
    assert not out.exists() or not any(out.iterdir())


def test_no_stable_terrain_left_is_a_clear_error(synth, tmp_path):
    z = synth.terrain(*synth.centres((64, 64)))
    a = synth.write_tif(tmp_path / "a.tif", z)
    b = synth.write_tif(tmp_path / "b.tif", z + 1)
    gj = tmp_path / "all.geojson"
    # covers everything (in the DSM's own CRS, legacy GeoJSON "crs" member)
    x0, y0, x1, y1 = synth.X0 - 100, synth.Y0 + 100, synth.X0 + 1000, synth.Y0 - 1000
    gj.write_text(json.dumps({"type": "Polygon", "crs": {"type": "name", "properties": {"name": synth.CRS}},
                              "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}))
    out = tmp_path / "out"
    with pytest.raises(NoStableTerrainError, match="no stable terrain"):
        compare_dsms(a, b, out, CompareSpec(stable_mask=str(gj)))
    assert not out.exists() or not any(out.iterdir())


def test_no_overlap_and_bad_geojson(synth, tmp_path):
    from affine import Affine

    z = synth.terrain(*synth.centres((32, 32)))
    a = synth.write_tif(tmp_path / "a.tif", z)
    b = synth.write_tif(tmp_path / "b.tif", z, transform=Affine(synth.RES, 0, synth.X0 + 5000, 0, -synth.RES, synth.Y0))
    with pytest.raises(NoOverlapError, match=r"a\.tif.*b\.tif"):
        compare_dsms(a, b, tmp_path / "o1")
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "Point", "coordinates": [0, 0]}')
    with pytest.raises(InputFileError, match=r"bad\.geojson.*Point"):
        compare_dsms(a, a, tmp_path / "o2", CompareSpec(stable_mask=str(bad)))


def test_cli_compare(synth, tmp_path, capsys):
    from tiledsm.cli import main

    z = synth.terrain(*synth.centres((96, 96)))
    a = synth.write_tif(tmp_path / "a.tif", z)
    b = synth.write_tif(tmp_path / "b.tif", synth.terrain(*synth.centres((96, 96), 0.0, 1.0)))
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--scheduler", "synchronous",
                 "--chunks", "32"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["coregistration"]["dx_px"] == pytest.approx(1.0, abs=0.02)
    assert (tmp_path / "o" / "metrics.json").exists()


def test_statistics_equal_numpy_on_the_stored_layers_in_any_chunking(synth, tmp_path):
    """The one-pass statistics (reduced while dh.zarr is written) against numpy on the stored dh/stable/slope_class."""
    from tiledsm.compare.stats import difference_statistics, slope_class_labels
    from tiledsm.io import open_product

    pre, other, *_ = _event(synth, (300, 260))
    runs = {}
    for chunks in (300, 64, 48):
        res = compare_dsms(synth.to_dataarray(pre, "pre"), synth.to_dataarray(other, "post"), tmp_path / f"c{chunks}",
                           CompareSpec(chunk=chunks), CompareOutput(cog=False, quicklook=False, report=False))
        runs[chunks] = res
    ds = open_product(runs[300].out_dir / "dh.zarr")
    dh, st, cls = ds["dh"].values, ds["stable"].values, ds["slope_class"].values
    width = runs[300].metrics["histogram"]["median_nmad_resolution_m"]
    groups = {"all": np.ones(dh.shape, bool), "stable": st == 1, "unstable": st == 2}
    groups.update({lab: (st == 1) & (cls == c) for c, lab in enumerate(slope_class_labels())})
    for chunks, res in runs.items():
        m = res.metrics
        for name, sel in groups.items():
            got = m["statistics"][name] if name in m["statistics"] else m["slope_classes"][name]
            exact = difference_statistics(dh[sel], reference=pre[sel])
            assert got["count"] == exact["count"], (chunks, name)
            for key in ("mean", "std", "rmse", "mae", "mre", "min", "max"):
                assert got[key] == pytest.approx(exact[key], rel=1e-6, abs=1e-9), (chunks, name, key)
            assert abs(got["median"] - exact["median"]) <= width, (chunks, name)
            assert abs(got["nmad"] - exact["nmad"]) <= 1.4826 * 2 * width, (chunks, name)
        # and the products do not depend on the chunking
        other_ds = open_product(res.out_dir / "dh.zarr")
        assert np.array_equal(other_ds["dh"].values, dh, equal_nan=True)
        assert np.array_equal(other_ds["stable"].values, st) and np.array_equal(other_ds["slope_class"].values, cls)


@pytest.mark.parametrize("option, value, problem", [
    ("--chunks", "8", "greater than or equal to 16"),
    ("--coreg", "icp", "unknown co-registration method 'icp'; known: none, nuth_kaab"),
    ("--nmad-k", "0", "greater than 0"),
    ("--max-slope", "95", "less than or equal to 90"),
])
def test_cli_compare_refuses_a_bad_option_naming_it(synth, tmp_path, capsys, option, value, problem):
    """A bad value is refused by the spec's validation, reported under the
    option: exit 2, one line, nothing written."""
    from tiledsm.cli import main

    a = synth.write_tif(tmp_path / "a.tif", synth.terrain(*synth.centres((32, 32))))
    out = tmp_path / "o"
    assert main(["compare", str(a), str(a), "--out", str(out), option, value]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"tiledsm compare: error: {option}: Input should be {problem}" or err == (
        f"tiledsm compare: error: {option}: {problem}"), err
    assert not out.exists()


def _compare_recipe(tmp_path, synth, shape=(96, 96), **sections) -> str:
    import yaml

    a = synth.write_tif(tmp_path / "a.tif", synth.terrain(*synth.centres(shape)))
    b = synth.write_tif(tmp_path / "b.tif", synth.terrain(*synth.centres(shape, 0.0, 1.0)))
    recipe = {"pipeline": "compare", "input": {"ref": str(a), "other": str(b)}, "cluster": {"scheduler": "synchronous"},
              **sections}
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return str(path)


@pytest.mark.parametrize("compare, field, problem", [
    ({"slope_classes": [5.0, 10.0]}, "compare.slope_classes", "[5.0, 10.0] must be increasing from 0"),
    ({"slope_classes": [0.0, 25.0, 10.0]}, "compare.slope_classes", "must be increasing from 0"),
    ({"coreg_fit": {"min_slope_deg": 50, "max_slope_deg": 40}}, "compare.coreg_fit",
     "need min_slope_deg < max_slope_deg, got 50.0 and 40.0"),
    ({"coreg_fit": {"shift_kernel": "lanczos"}}, "compare.coreg_fit.shift_kernel", "lanczos"),
    ({"coreg_fit": {"max_samples": -1}}, "compare.coreg_fit.max_samples", "greater than or equal to 0"),
    ({"coreg_fit": {"vertical": "mode"}}, "compare.coreg_fit.vertical", "'median' or 'mean'"),
    ({"resampling": "bicubic_spline"}, "compare.resampling", "unknown resampling 'bicubic_spline'"),
])
def test_run_refuses_a_bad_advanced_field_naming_it(synth, tmp_path, capsys, compare, field, problem):
    """The checks of the former parameter dataclasses are the spec's
    validators: ``tiledsm run`` of a recipe with a bad advanced field exits 2
    naming the field, before anything is written."""
    from tiledsm.cli import main

    out = tmp_path / "o"
    assert main(["run", _compare_recipe(tmp_path, synth, compare=compare), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{field}: " in err and problem in err, err
    assert not out.exists()


def test_run_passes_the_advanced_fields_to_the_stage(synth, tmp_path, capsys):
    """Recipe-only fields reach the comparison: two slope classes, the exact
    fit (``max_samples: 0``), no figures; metrics.json records the sections."""
    from tiledsm.cli import main

    compare = {"slope_classes": [0.0, 30.0], "coreg_fit": {"max_samples": 0, "shift_kernel": "linear"}, "chunk": 32}
    output = {"quicklook": False, "report": False}
    out = tmp_path / "o"
    assert main(["run", _compare_recipe(tmp_path, synth, compare=compare, output=output), "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["slope_classes"]) == ["[0%;30%[", "[30%;inf["]
    assert m["coregistration"]["dx_px"] == pytest.approx(1.0, abs=0.02)
    assert m["params"]["compare"]["coreg_fit"]["max_samples"] == 0 and m["params"]["output"]["quicklook"] is False
    assert not list(out.glob("*.png")) and not (out / "report.html").exists() and (out / "dh.tif").exists()


def test_the_deformation_recipe_compares_with_the_compare_spec():
    """``compare:`` of a deformation recipe is the comparison stage's own
    spec (plus the throw's strips), so its advanced fields are the same."""
    from tiledsm.compare import CompareSpec
    from tiledsm.pipelines import load_recipe

    r = load_recipe(Path(__file__).parents[2] / "recipes" / "deformation.yaml")
    assert isinstance(r.compare, CompareSpec)
    assert (r.compare.coreg, r.compare.chunk, r.compare.strip) == ("nuth_kaab", 256, (3.0, 20.0))
    assert r.compare.coreg_fit == CompareSpec().coreg_fit and r.compare.nmad_k == 5.0
    assert type(r.compare)().chunk == 512  # a deformation's default chunk


def test_cli_compare_reads_zarr_stores(synth, tmp_path, capsys):
    """``tiledsm compare`` of two tiledsm stores (``dsm.zarr`` of two runs),
    as its help says: the plan read them with GDAL, which opens a zarr
    folder with no band, and failed with an IndexError."""
    from tiledsm.cli import main
    from tiledsm.io import write_zarr

    a = write_zarr(synth.to_dataarray(synth.terrain(*synth.centres((96, 96))), "height").chunk(32), tmp_path / "a.zarr")
    b = write_zarr(synth.to_dataarray(synth.terrain(*synth.centres((96, 96), 0.0, 1.0)), "height").chunk(32),
                   tmp_path / "b.zarr")
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--scheduler", "synchronous", "--dry-run"]) == 0
    assert "96 x 96 cells of 10" in capsys.readouterr().out
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--scheduler", "synchronous", "--chunks", "32"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["coregistration"]["dx_px"] == pytest.approx(1.0, abs=0.02)


def test_compare_on_threads_equals_the_synchronous_run(synth, tmp_path):
    """``--scheduler threads`` (no worker processes): the same products as the
    in-thread run, and the work really ran on the threaded scheduler."""
    import dask

    from tiledsm.cluster import ClusterConfig, compute_context

    ref = synth.to_dataarray(synth.terrain(*synth.centres((96, 96))), "height")
    other = synth.to_dataarray(synth.terrain(*synth.centres((96, 96), 0.0, 1.0)) + 0.5, "height")
    spec, output = CompareSpec(chunk=32), CompareOutput(quicklook=False, report=False, cog=False)
    results = {}
    for scheduler in ("synchronous", "threads"):
        with compute_context(ClusterConfig(scheduler=scheduler, workers=2, progress=False)):
            assert dask.base.get_scheduler() is (dask.threaded.get if scheduler == "threads" else dask.local.get_sync)
            results[scheduler] = compare_dsms(ref, other, tmp_path / scheduler, spec, output)
    from tiledsm.io import open_product

    a, b = (open_product(results[s].products["dh_zarr"]) for s in ("synchronous", "threads"))
    np.testing.assert_array_equal(a["dh"].values, b["dh"].values)
    assert results["threads"].metrics["statistics"] == results["synchronous"].metrics["statistics"]


def test_cli_compare_runs_on_threads_unless_told_otherwise(synth, tmp_path, capsys):
    """Without --scheduler or --cluster, compare plans threads of its own
    process; a cluster file of kind local keeps worker processes."""
    from tiledsm.cli import main
    from tiledsm.io import write_zarr

    a = write_zarr(synth.to_dataarray(synth.terrain(*synth.centres((64, 64))), "height").chunk(32), tmp_path / "a.zarr")
    b = write_zarr(synth.to_dataarray(synth.terrain(*synth.centres((64, 64), 0.0, 1.0)), "height").chunk(32),
                   tmp_path / "b.zarr")
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--workers", "2", "--dry-run"]) == 0
    assert "in this process: 2 threads" in capsys.readouterr().out
    local = tmp_path / "local.yaml"
    local.write_text("kind: local\nworkers: 2\n")
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--cluster", str(local), "--dry-run"]) == 0
    assert "local cluster: 2 single-threaded worker processes" in capsys.readouterr().out
