"""``tiledsm run --dry-run`` of the deformation and sr_dsm recipes: every DSM
the run makes planned (grid, chunks, levels, memory) before anything exists,
and the chunk-wise scores against whole-array oracles."""

import dataclasses
import re

import dask.array as da
import numpy as np
import pytest
import xarray as xr
import yaml

from tiledsm.cli import main


def _recipe(tmp_path, doc):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def _rows(text: str, key: str) -> list[str]:
    return [line.split(key, 1)[1].strip() for line in text.splitlines() if line.strip().startswith(key + " ")]


def test_deformation_dry_run_plans_both_epochs_on_the_scene_grid(tmp_path, capsys):
    """The dry run of a synthetic event shows both epochs' grid, chunks,
    levels and memory, writes nothing, and its grid is the one the scene
    then gets (oracle: the truth grid make_scene writes)."""
    from tiledsm.io.grids import grid_like
    from tiledsm.synth import make_scene

    doc = {"pipeline": "deformation", "input": {"synth": {"size": 128, "gsd": 0.5, "seed": 3}},
           "grid": {"chunk": 64}, "compare": {"chunk": 64}}
    out = tmp_path / "run"
    assert main(["run", _recipe(tmp_path, doc), "--out", str(out), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert not out.exists()
    for epoch in ("pre", "post"):
        (grid,) = _rows(text, f"{epoch} grid")
        assert "128 x 128 cells" in grid and "chunks of 64: 2 x 2 = 4" in grid
        assert _rows(text, f"{epoch} levels") and re.search(r"L0: 128 x 128 cells of 0.5 m", text)
        (memory,) = _rows(text, f"{epoch} memory")
        assert re.match(r"~\d+\.\d\d GiB \(\d+ MiB\) per worker", memory)
    assert "heights come from the scene's tie points" in text
    scene = make_scene(tmp_path / "scene", size=128, gsd=0.5, seed=3, workers=1)  # the grid does not depend on the event
    truth = grid_like(scene.truth_dsm)
    bounds = "(" + ", ".join(f"{b:.1f}" for b in truth.bounds) + ")"
    assert bounds in _rows(text, "pre grid")[0] and bounds in _rows(text, "post grid")[0]


def test_sr_dsm_dry_run_plans_every_dsm(tmp_path, capsys):
    """HR, LR (DSM upscale: half the cells each way) and each SR method."""
    doc = {"pipeline": "sr_dsm", "input": {"synth": {"size": 128, "gsd": 0.5}},
           "sr": {"models": ["dsm_upscale", "bicubic"]}, "grid": {"chunk": 64}}
    out = tmp_path / "run"
    assert main(["run", _recipe(tmp_path, doc), "--out", str(out), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert not out.exists()
    assert "128 x 128 cells" in _rows(text, "hr grid")[0] and "128 x 128 cells" in _rows(text, "bicubic grid")[0]
    assert "64 x 64 cells" in _rows(text, "lr grid")[0] and "1 m cells" in _rows(text, "lr grid")[0]
    for name in ("hr", "lr", "bicubic"):
        assert _rows(text, f"{name} memory"), name


# ---------------------------------------------------------------------------- chunk-wise against whole arrays
def _dh(rng, shape=(300, 260), chunk=64):
    y = 1000.0 - (np.arange(shape[0]) + 0.5) * 0.5
    x = 500.0 + (np.arange(shape[1]) + 0.5) * 0.5
    values = rng.normal(0.0, 0.3, shape)
    values[rng.random(shape) < 0.05] = np.nan
    return xr.DataArray(da.from_array(values, chunks=chunk), dims=("y", "x"), coords={"y": y, "x": x}), values, x, y


def test_strips_lazy_equal_the_whole_grid_throw():
    from tiledsm.workflows.fault import Fault, strips_lazy, throw_across, throw_of_strips

    rng = np.random.default_rng(0)
    dh, values, x, y = _dh(rng)
    fault = Fault((560.0, 900.0), (0.3, 1.0))
    values[:, :] += np.where(fault.signed_distance(x, y) > 0, 2.0, 0.0)
    dh = dh.copy(data=da.from_array(values, chunks=64))
    valid = rng.random(values.shape) < 0.9
    whole = throw_across(values, fault.signed_distance(x, y), (3.0, 20.0), valid)
    lazy = throw_of_strips(*strips_lazy(dh, fault, (3.0, 20.0), da.from_array(valid, chunks=64)), (3.0, 20.0))
    assert lazy == whole and whole["throw"] == pytest.approx(2.0, abs=0.1)


def test_error_stats_lazy_against_numpy():
    from tiledsm.evaluate.deformation import error_stats_lazy
    from tiledsm.workflows.fault import error_stats

    rng = np.random.default_rng(1)
    _, values, _, _ = _dh(rng)
    keep = rng.random(values.shape) < 0.7
    lazy = error_stats_lazy(da.from_array(values, chunks=64), da.from_array(keep, chunks=64))
    whole = error_stats(values[keep & np.isfinite(values)])
    assert lazy["count"] == whole["count"]
    assert lazy["rmse"] == pytest.approx(whole["rmse"], rel=1e-12) and lazy["mean"] == pytest.approx(whole["mean"], abs=1e-12)
    bin_m = (np.nanmax(values[keep]) - np.nanmin(values[keep])) / 2**18
    for key in ("median", "nmad", "le95"):
        assert lazy[key] == pytest.approx(whole[key], abs=3 * bin_m), key


def test_image_quality_lazy_equals_whole_images():
    from tiledsm.workflows.sr_scores import image_quality, image_quality_lazy

    rng = np.random.default_rng(2)
    hr = rng.uniform(0, 4095, (200, 180))
    sr = hr[:198, :178] + rng.normal(0, 30, (198, 178))
    sr[50:53, 60:64] = np.nan
    whole = image_quality(hr, sr, peak=4095.0, border=2)
    lazy = image_quality_lazy(da.from_array(hr, chunks=64), da.from_array(sr, chunks=48), peak=4095.0, border=2)
    assert lazy["psnr_db"] == pytest.approx(whole["psnr_db"], abs=1e-9)
    assert lazy["ssim"] == pytest.approx(whole["ssim"], abs=1e-9)


def test_upsample_dsm_in_blocks_equals_one_block():
    from tiledsm.geometry.grid import GroundGrid
    from tiledsm.workflows.sr_dsm import lr_grid, upsample_dsm

    grid = GroundGrid("EPSG:32631", 675000.0, 4896000.0, 0.5, 150, 130, 32)
    lr = lr_grid(grid, 2)
    rng = np.random.default_rng(3)
    values = rng.normal(300.0, 5.0, (lr.height, lr.width)).astype(np.float32)
    values[10:13, 7:9] = np.nan
    low = xr.DataArray(values, dims=("y", "x"), coords={"y": lr.y, "x": lr.x})
    whole = upsample_dsm(low, dataclasses.replace(grid, chunk=4096)).values  # one block
    tiled = upsample_dsm(low.chunk(16), grid).values
    np.testing.assert_array_equal(tiled, whole)
