"""SR -> DSM workflow (tiledsm.workflows.sr_dsm): a small synthetic scene run
end to end, every row checked against an independent oracle where one exists."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
import xarray as xr
import yaml

from tiledsm.cluster import ClusterConfig
from tiledsm.errors import RecipeError
from tiledsm.geometry import RPC
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.pipelines import load_recipe, run_recipe
from tiledsm.workflows.sr_dsm import METHODS, UPSCALE, lr_grid, upsample_dsm
from tiledsm.workflows.sr_scores import REGIONS

SYNC = ClusterConfig(scheduler="synchronous", progress=False)
SR_MODELS = [m for m in METHODS if m != UPSCALE]


def _write_recipe(path, **fields):
    doc = {"pipeline": "sr_dsm", **fields}
    path.write_text(yaml.safe_dump(doc))
    return path


def _read(path):
    with rasterio.open(path) as src:
        return src.read(1, masked=True).astype(np.float64).filled(np.nan)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The workflow on a 192 px synthetic scene, every method, synchronous,
    then scored by ``tiledsm evaluate``."""
    tmp = tmp_path_factory.mktemp("sr_dsm")
    recipe = load_recipe(_write_recipe(
        tmp / "sr_dsm.yaml",
        input={"synth": {"size": 192, "gsd": 0.5, "bh": 0.4, "seed": 1}},
        sr={"models": list(METHODS)},
        grid={"chunk": 128},
        output={"cog": True, "quicklook": False},
    ))
    out = tmp / "run"
    metrics = run_recipe(recipe, out, SYNC)
    # the DSM tables are the evaluation's (tiledsm evaluate), beside the run's own rows
    from tiledsm.cli import main
    from tiledsm.evaluate.sr_dsm import with_tables

    assert main(["evaluate", str(out)]) == 0
    return out, with_tables(metrics, json.loads((out / "evaluation.json").read_text())["scores"])


def test_every_method_has_its_rows_and_files(run):
    out, metrics = run
    assert list(metrics["methods"]) == list(METHODS)
    assert json.loads((out / "metrics.json").read_text())["methods"].keys() == metrics["methods"].keys()
    assert (out / "recipe.resolved.yaml").exists()
    assert "**Table 2.**" not in (out / "report.md").read_text()  # the run's own report: Table 1
    report = (out / "evaluation" / "report.md").read_text()
    table1, table2 = report.split("**Table 2.**")[0], report.split("**Table 2.**")[1].split("**Table 3.**")[0]
    for label in ("Bicubic", "SRCNN", "VDSR", "SRMD"):
        assert f"| {label} |" in table1 and f"| {label} |" in table2
    assert "| DSM upscale |" in table2 and "DSM upscale" not in table1
    for name in SR_MODELS:
        row = metrics["methods"][name]
        assert 20 < row["image"]["psnr_db"] < 60 and 0.5 < row["image"]["ssim"] <= 1
        for i in (0, 1):
            assert (out / name / f"sr_view_{i}.tif").exists()
        assert (out / name / "dsm.tif").exists()
    for name in METHODS:
        for key in ("vs_hr", "vs_truth_visible"):
            s = metrics["methods"][name][key]
            assert np.isfinite([s["rmse"], s["mre"], s["nmad"], s["completeness"], s["blunder_rate"]]).all()
    # the four-region breakdown: every region holds cells, each scored for the HR pair and every method
    regions = metrics["regions"]
    assert list(regions["tables"]) == list(REGIONS) and regions["dsms"] == ["hr", *METHODS]
    for region, table in regions["tables"].items():
        assert table["common"]["count"] > 100, region
        assert set(table["scores"]) == {"hr", *METHODS}
    assert "**Table 4.** Four-region breakdown" in report
    assert (out / "evaluation" / "blunders.png").stat().st_size > 10_000


def test_tables_are_scored_on_common_cells(run):
    """Every row of a table is scored on the same cells, no more than any
    row's own valid cells; the report says how many."""
    out, metrics = run
    report = (out / "evaluation" / "report.md").read_text()
    rows = {"vs_hr": metrics["methods"], "vs_truth_visible": {"hr": metrics["hr"], **metrics["methods"]}}
    for key, table in rows.items():
        common = metrics["common"][key]
        assert common["dsms"] == list(table)
        assert 0.5 < common["fraction"] <= min(r[key]["completeness"] for r in table.values())
        for name, r in table.items():
            assert r[key]["count"] == common["count"], (key, name)
            assert r[key]["cells"] == common["cells"] and r[key]["valid"] >= common["count"]
        assert f"Scored on {common['count']} common cells ({100 * common['fraction']:.1f} % of the {common['cells']} cells" in report


def test_bicubic_row_against_skimage_and_opencv(run):
    """Table 1's bicubic PSNR/SSIM recomputed with scikit-image, and the
    bicubic SR image itself against OpenCV's INTER_CUBIC resize."""
    import cv2
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    out, metrics = run
    b = 2
    for i in (0, 1):
        hr = _read(out / "scene" / f"view_{i}.tif")
        sr = _read(out / "bicubic" / f"sr_view_{i}.tif")
        hr = hr[: sr.shape[0], : sr.shape[1]]
        q = metrics["methods"]["bicubic"]["image"]["views"][i]
        crop = (slice(b, -b), slice(b, -b))
        assert q["psnr_db"] == pytest.approx(peak_signal_noise_ratio(hr[crop], sr[crop], data_range=4095), abs=1e-9)
        assert q["ssim"] == pytest.approx(structural_similarity(hr[crop], sr[crop], data_range=4095, win_size=7), abs=1e-9)
        lr = _read(out / "lr" / f"view_{i}.tif").astype(np.float32)
        ref = cv2.resize(lr, (2 * lr.shape[1], 2 * lr.shape[0]), interpolation=cv2.INTER_CUBIC)
        assert np.abs(ref - sr).max() < 1e-2  # DN of 4095: float32 round-off
    mean = np.mean([q["psnr_db"] for q in metrics["methods"]["bicubic"]["image"]["views"]])
    assert metrics["methods"]["bicubic"]["image"]["psnr_db"] == pytest.approx(mean)


def test_sr_images_carry_the_hr_camera(run):
    """LR camera = HR.scaled(1/2), SR camera = LR.scaled(2): the SR image's
    RPC projects ground points where the HR image's does."""
    out, _ = run
    for i in (0, 1):
        with rasterio.open(out / "scene" / f"view_{i}.tif") as a, rasterio.open(out / "srcnn" / f"sr_view_{i}.tif") as c:
            hr_rpc, sr_rpc = RPC.from_gdal(a.tags(ns="RPC")), RPC.from_gdal(c.tags(ns="RPC"))
        lon, lat = hr_rpc.lon_off + 0.001, hr_rpc.lat_off - 0.001
        np.testing.assert_allclose(sr_rpc.project(lon, lat, hr_rpc.height_off), hr_rpc.project(lon, lat, hr_rpc.height_off), atol=1e-6)


def test_dsm_upscale_is_the_lr_dsm_interpolated(run):
    """The DSM-upscale row's DSM equals scipy's bilinear interpolation of the
    stored LR DSM (cells whose four neighbours have a height)."""
    from scipy.interpolate import RegularGridInterpolator

    from tiledsm.io import open_product

    out, metrics = run
    lr = open_product(out / "lr" / "dsm.zarr")["height"].load()
    up = xr.open_dataarray(out / UPSCALE / "dsm.tif", engine="rasterio").squeeze("band", drop=True)
    truth_grid = grid_like(out / "scene" / "truth_dsm.tif")
    assert float(abs(lr.x[1] - lr.x[0])) == pytest.approx(2 * truth_grid.resolution)
    assert up.shape == truth_grid.shape
    y, x = lr.y.values, lr.x.values
    interp = RegularGridInterpolator((y[::-1], x), lr.values[::-1], method="linear", bounds_error=False)
    yy, xx = np.meshgrid(up.y.values, up.x.values, indexing="ij")
    ref = interp(np.stack([yy, xx], -1))
    both = np.isfinite(ref)
    assert both.mean() > 0.5  # measured 0.64: the LR DSM of a small scene has holes
    np.testing.assert_allclose(up.values[both], ref[both], atol=1e-3)
    # holes keep their size: where the oracle is NaN only because a neighbour is
    assert np.isfinite(up.values).mean() >= both.mean()
    assert metrics["methods"][UPSCALE]["dsm"]["lr_grid_resolution"] == pytest.approx(2 * truth_grid.resolution)


def test_sr_dsms_against_truth(run):
    """Measured on this scene (seed 1, 192 px), NMAD on the visible ground
    cells where every DSM has a height (81 % of them): 0.22 m (HR pair),
    0.31-0.33 m (SR pairs), 0.45 m (DSM upscale); the bounds leave some
    margin."""
    _, metrics = run
    hr = metrics["hr"]["vs_truth_visible"]
    assert hr["nmad"] < 0.3 and hr["completeness"] > 0.85
    upscale = metrics["methods"][UPSCALE]["vs_truth_visible"]
    for name in SR_MODELS:
        s = metrics["methods"][name]["vs_truth_visible"]
        assert s["nmad"] < 0.45, (name, s)
        assert s["nmad"] < upscale["nmad"], (name, s, upscale)  # the paper's claim, on this scene
        assert s["completeness"] > 0.8, (name, s)
        assert abs(s["median"]) < 0.1, (name, s)
        # every SR-DSM is close to the HR-pair DSM on most cells
        assert metrics["methods"][name]["vs_hr"]["nmad"] < 0.25, name


def test_shipped_srmd_beats_bicubic_on_heldout_blur_noise():
    """The shipped SRMD x2 against bicubic on the held-out camera image
    (never trained on), blurred (sigma 1.2 HR px), decimated at the pixel
    centres and noisy (10/255)."""
    from tiledsm.sr.registry import load_pretrained
    from tiledsm.sr.train import evaluate, skimage_images

    cam = skimage_images(["camera"])["camera"][128:384, 128:384]
    model = load_pretrained("srmd", 2)
    assert model.card["steps"] > 0 and model.card["heldout_eval"]["centred"]
    res = evaluate(model, 2, {"camera": cam}, degradation="blur_noise", blur_sigma=1.2, noise=10 / 255, centred=True)
    assert res["camera"]["model"] > res["camera"]["bicubic"] + 0.5, res


def test_shipped_srmd_tiles_equal_whole_image():
    """The shipped SRMD (bicubic skip) keeps tiled inference exact."""
    import dask

    from tiledsm.sr.infer import sr_array, super_resolve
    from tiledsm.sr.registry import load_pretrained

    model = load_pretrained("srmd", 2)
    img = np.random.default_rng(0).uniform(0, 4095, (80, 72)).astype(np.float32)
    whole = sr_array(img, model, value_scale=4095, blur_sigma=0.8, noise=5.0)
    scene = xr.DataArray(img, dims=("y", "x")).chunk({"y": 32, "x": 32})
    with dask.config.set(scheduler="synchronous"):
        tiled = super_resolve(scene, model, 2, value_scale=4095, blur_sigma=0.8, noise=5.0).values
    assert np.abs(tiled - whole).max() <= 1e-5 * 4095


def test_lr_grid_and_upsample_reproduce_a_plane():
    g = GroundGrid("EPSG:32631", 1000.0, 5000.0, 0.5, 11, 9, 64)
    lg = lr_grid(g, 2)
    assert (lg.resolution, lg.width, lg.height, lg.x0, lg.y0) == (1.0, 6, 5, 1000.0, 5000.0)
    plane = lambda x, y: 3 + 0.1 * (x - 1000) - 0.2 * (y - 5000)  # noqa: E731
    h = xr.DataArray(plane(*np.meshgrid(lg.x, lg.y)), dims=("y", "x"), coords={"y": lg.y, "x": lg.x})
    up = upsample_dsm(h, g)
    np.testing.assert_allclose(up.values, plane(*np.meshgrid(g.x, g.y)), atol=1e-5)  # edges extrapolated
    assert up.rio.transform() == g.transform
    h[2, 2] = np.nan  # one LR hole -> exactly the 2 x 2 fine cells it covers
    assert np.argwhere(np.isnan(upsample_dsm(h, g).values)).tolist() == [[4, 4], [4, 5], [5, 4], [5, 5]]


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"sr": {"modles": ["srcnn"]}}, r"sr\.modles: Extra inputs are not permitted"),
        ({"sr": {"models": ["srcnn", "edsr"]}}, r"sr\.models: .*unknown method\(s\) \['edsr'\]"),
        ({"sr": {"scale": 1}}, r"sr\.scale"),
        ({"input": {"images": ["a.tif", "b.tif", "c.tif"]}}, r"takes a pair \(2 images\), got 3"),
        ({"input": {"images": ["a.tif", "b.tif"], "rpcs": ["a.rpc", None]}}, r"input\.rpcs: sr_dsm needs the cameras"),
    ],
)
def test_wrong_recipe_field_is_a_recipe_error(tmp_path, fields, message):
    fields = {"input": {"synth": {"size": 128}}, **fields}
    path = _write_recipe(tmp_path / "bad.yaml", **fields)
    with pytest.raises(RecipeError, match=message) as err:
        load_recipe(path)
    assert str(path) in str(err.value)


def test_missing_input_image_names_the_file(tmp_path):
    path = _write_recipe(tmp_path / "r.yaml", input={"images": ["nope_0.tif", "nope_1.tif"]})
    recipe = load_recipe(path)
    from tiledsm.errors import TiledsmError

    with pytest.raises(TiledsmError, match=r"nope_0\.tif: input\.images: no such file"):
        run_recipe(recipe, tmp_path / "run", SYNC)
