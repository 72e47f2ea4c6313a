"""The DSM stage against truth, across chunkings, schedulers and bad input."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr

from tiledsm.cluster import ClusterConfig
from tiledsm.dsm import DSMParams, dsm_from_pair
from tiledsm.errors import NoOverlapError, TiledsmError
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.io import open_product
from tiledsm.workflows.common import reference_on_grid, write_dsm_products
from tiledsm.synth import make_scene

SYNC = ClusterConfig(scheduler="synchronous", progress=False)


def nmad(d: np.ndarray) -> float:
    d = d[np.isfinite(d)]
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def _compute(ds: xr.Dataset, out: Path, cluster: ClusterConfig = SYNC) -> xr.Dataset:
    write_dsm_products(ds, out, cluster=cluster, cog=False, quicklook=False)
    return open_product(out / "dsm.zarr").load()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # the acceptance scene: 1024 x 1024 px, GSD 0.5 m, B/H 0.4
    return make_scene(tmp_path_factory.mktemp("scene"), size=1024, gsd=0.5, bh=0.4, seed=3)


@pytest.fixture(scope="module")
def scene_dsms(scene, tmp_path_factory):
    """The same scene on the truth grid with two chunkings."""
    out = {}
    for chunk in (256, 1024):
        grid = grid_like(scene.truth_dsm, chunk=chunk)
        ds, report = dsm_from_pair(*scene.views, grid=grid, params=DSMParams(chunk=chunk))
        out[chunk] = _compute(ds, tmp_path_factory.mktemp(f"dsm{chunk}"))
    return out


def _visible(scene, like):
    mask_path = getattr(scene, "visible_mask", None)
    if mask_path is None:
        return np.ones(like.shape, bool)
    return reference_on_grid(mask_path, like).values > 0.5


def test_synthetic_truth_accuracy(scene, scene_dsms):
    dsm = scene_dsms[1024]["height"]
    truth = reference_on_grid(scene.truth_dsm, dsm).values
    vis = _visible(scene, dsm) & np.isfinite(truth)
    # leave out a 2 % frame: the sensor footprint does not cover the grid's corners
    frame = np.zeros_like(vis)
    m = int(0.02 * vis.shape[0]) + 1
    frame[m:-m, m:-m] = True
    sel = vis & frame
    d = dsm.values[sel] - truth[sel]
    completeness = float(np.isfinite(d).mean())
    assert nmad(d) <= 0.5, f"NMAD {nmad(d):.3f} m"
    assert completeness >= 0.95, f"completeness {completeness:.3f}"


def test_chunking_is_seamless(scene_dsms):
    a = scene_dsms[256]["height"].values
    b = scene_dsms[1024]["height"].values
    d = np.abs(a - b)
    assert np.nanmedian(d) <= 0.05
    # |diff| on the chunk borders of the 256 chunking is no worse than inside
    border = np.zeros(a.shape, bool)
    for k in range(256, a.shape[0], 256):
        border[k - 1 : k + 1, :] = True
    for k in range(256, a.shape[1], 256):
        border[:, k - 1 : k + 1] = True
    on, off = d[border & np.isfinite(d)], d[~border & np.isfinite(d)]
    assert np.mean(on > 0.5) <= np.mean(off > 0.5) + 0.01
    # and the valid masks agree almost everywhere
    assert np.mean(np.isfinite(a) != np.isfinite(b)) < 0.01


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_distributed_cluster_matches_local(scene, scene_dsms, tmp_path):
    """`dask scheduler` + two `dask worker` processes give the identical DSM."""
    port = _free_port()
    bindir = Path(sys.executable).parent
    sched = subprocess.Popen(
        [str(bindir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    workers = []
    try:
        addr = f"tcp://127.0.0.1:{port}"
        for _ in range(2):
            workers.append(
                subprocess.Popen(
                    [str(bindir / "dask"), "worker", addr, "--nthreads", "1", "--no-dashboard"],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )
        from distributed import Client

        deadline = time.time() + 60
        while True:
            try:
                with Client(addr, timeout=5) as c:
                    if len(c.scheduler_info()["workers"]) == 2:
                        break
            except OSError:
                pass
            if time.time() > deadline:
                pytest.fail("dask scheduler/workers did not start within 60 s")
            time.sleep(0.5)
        grid = grid_like(scene.truth_dsm, chunk=1024)
        ds, _ = dsm_from_pair(*scene.views, grid=grid, params=DSMParams(chunk=1024))
        remote = _compute(ds, tmp_path / "remote", ClusterConfig(scheduler=addr, progress=False))
    finally:
        for p in workers + [sched]:
            p.terminate()
        for p in workers + [sched]:
            p.wait(timeout=30)
    np.testing.assert_array_equal(remote["height"].values, scene_dsms[1024]["height"].values)


def test_threads_give_the_synchronous_dsm(scene, scene_dsms, tmp_path):
    """``tiledsm dsm``'s default scheduler, W threads of the calling process:
    the identical DSM (bit for bit) as the in-thread run, computed on the
    threaded scheduler."""
    import dask

    from tiledsm.cluster import compute_context

    grid = grid_like(scene.truth_dsm, chunk=256)
    ds, _ = dsm_from_pair(*scene.views, grid=grid, params=DSMParams(chunk=256))
    threads = ClusterConfig(scheduler="threads", workers=2, progress=False)
    with compute_context(threads):
        assert dask.base.get_scheduler() is dask.threaded.get
    got = _compute(ds, tmp_path / "threads", threads)
    np.testing.assert_array_equal(got["height"].values, scene_dsms[256]["height"].values)
    np.testing.assert_array_equal(got["confidence"].values, scene_dsms[256]["confidence"].values)


def test_cli_dsm_runs_on_threads_unless_told_otherwise(scene, tmp_path, capsys):
    """Without --scheduler or --cluster, ``tiledsm dsm`` plans threads of its
    own process; a cluster file of kind local keeps worker processes."""
    from tiledsm.cli import main

    args = ["dsm", *map(str, scene.views), "--like", str(scene.truth_dsm), "--out", str(tmp_path / "o")]
    assert main([*args, "--workers", "2", "--dry-run"]) == 0
    assert "in this process: 2 threads" in capsys.readouterr().out
    local = tmp_path / "local.yaml"
    local.write_text("kind: local\nworkers: 2\n")
    assert main([*args, "--cluster", str(local), "--dry-run"]) == 0
    assert "local cluster: 2 single-threaded worker processes" in capsys.readouterr().out


def test_cli_dsm_tif_overviews_are_gdals(scene, tmp_path):
    """``dsm.tif`` of ``tiledsm dsm`` (a 768 x 576-cell part of the
    synthetic scene: one overview level, averaged while the rows stream)
    holds ``dsm.zarr``'s heights, and its overview equals the one GDAL's
    ``COG`` driver averages from the same grid (the oracle: ``write_cog``
    with ``overviews="gdal"``), NaN holes included."""
    import rasterio

    from tiledsm.cli import main
    from tiledsm.io import write_cog
    from tiledsm.io.overviews import cog_overview_count, streamable_overviews

    with rasterio.open(scene.truth_dsm) as src:
        crs, res, t = src.crs.to_string(), abs(src.res[0]), src.transform
    x0, y0 = t.c + 128 * t.a, t.f + 128 * t.e
    out = tmp_path / "out"
    bounds = [x0, y0 - 576 * res, x0 + 768 * res, y0]
    assert main(["dsm", *map(str, scene.views), "--crs", crs, "--resolution", str(res), "--bounds", *map(str, bounds),
                 "--out", str(out), "--chunk", "256", "--workers", "2", "--scheduler", "threads",
                 "--no-progress"]) == 0
    height = open_product(out / "dsm.zarr")["height"]
    assert height.shape == (576, 768) and cog_overview_count(height.shape, 512) == 1
    assert streamable_overviews(height.shape, height.dtype, 1)  # the streamed route, not GDAL's
    with rasterio.open(out / "dsm.tif") as cog:
        assert cog.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and cog.overviews(1) == [2]
        np.testing.assert_array_equal(cog.read(1), height.values)
    assert np.isnan(height.values).any()
    gdal = write_cog(height, tmp_path / "gdal.tif", overviews="gdal")
    with rasterio.open(out / "dsm.tif", overview_level=0) as ours, rasterio.open(gdal, overview_level=0) as want:
        got, expect = ours.read(1), want.read(1)
    assert got.shape == (288, 384) and np.isnan(expect).any()
    np.testing.assert_array_equal(got, expect)


def test_cli_dsm_reference_scores_match_numpy(scene, tmp_path):
    """``tiledsm dsm --reference`` on a 320 x 320-cell part of the synthetic
    scene (chunks of 128): the statistics metrics.json gives (streamed chunk
    by chunk, after the exports) against numpy on the written dsm.tif and
    the truth: counts exact, moments to float32 rounding, median and NMAD
    within the histogram's stated bounds."""
    import json

    import rasterio

    from tiledsm.cli import main

    with rasterio.open(scene.truth_dsm) as src:
        crs, res, t = src.crs.to_string(), abs(src.res[0]), src.transform
    x0, y0 = t.c + 352 * t.a, t.f + 352 * t.e  # 352 cells in from the truth's corner
    out = tmp_path / "ref"
    bounds = [x0, y0 - 320 * res, x0 + 320 * res, y0]
    assert main(["dsm", *map(str, scene.views), "--crs", crs, "--resolution", str(res),
                 "--bounds", *map(str, bounds), "--reference", str(scene.truth_dsm), "--out", str(out),
                 "--chunk", "128", "--workers", "2", "--no-progress"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    got = metrics["vs_reference"]
    with rasterio.open(out / "dsm.tif") as a, rasterio.open(scene.truth_dsm) as b:
        dsm = a.read(1, masked=True).filled(np.nan).astype(np.float64)
        window = rasterio.windows.from_bounds(*a.bounds, transform=b.transform)
        ref = b.read(1, window=window, masked=True).filled(np.nan).astype(np.float64)
    assert dsm.shape == ref.shape == (320, 320)
    evaluated = np.isfinite(ref)
    d = (dsm - ref)[evaluated]
    v = d[np.isfinite(d)]
    assert (got["cells"], got["count"]) == (evaluated.sum(), v.size) and v.size > 0.8 * evaluated.sum()
    assert got["completeness"] == pytest.approx(v.size / evaluated.sum(), rel=1e-12)
    for key, want in (("mean", v.mean()), ("rmse", np.sqrt(np.mean(v * v))), ("min", v.min()), ("max", v.max())):
        assert got[key] == pytest.approx(want, rel=1e-5, abs=1e-5), key
    bin_width = (v.max() - v.min()) / 2**18
    assert abs(got["median"] - np.median(v)) <= bin_width + 1e-5
    assert got["nmad"] == pytest.approx(nmad(v), abs=1.4826 * 1.5 * bin_width + 1e-5)
    assert abs(got["coregistered"]["offset_px"][0]) < 0.2 and abs(got["coregistered"]["offset_px"][1]) < 0.2
    assert metrics["timings"]["score_s"] > 0 and (out / "dsm_error.png").stat().st_size > 10_000


def test_views_without_overlap(shared_data, tmp_path):
    a = shared_data("rpc_models", "shareloc", "wv3_20.NTF")
    b = shared_data("rpc_models", "shareloc", "wv3_30.NTF")
    with pytest.raises(NoOverlapError) as e:
        ds, _ = dsm_from_pair(a, b, params=DSMParams(height_range=(0.0, 200.0)))
    assert "wv3_20" in str(e.value) or "wv3_30" in str(e.value)


def test_grid_outside_footprint_gives_nan_chunks(scene, tmp_path):
    g = grid_like(scene.truth_dsm, chunk=64)
    far = GroundGrid(g.crs, g.x0 + 50_000, g.y0, g.resolution, 128, 128, chunk=64)
    ds, _ = dsm_from_pair(*scene.views, grid=far, params=DSMParams(chunk=64, height_range=scene.height_range))
    out = _compute(ds, tmp_path / "far")
    assert np.isnan(out["height"].values).all()


def test_all_nodata_view(scene, tmp_path):
    blank = tmp_path / "blank.tif"
    with rasterio.open(scene.views[1]) as src:
        profile = src.profile
        profile.update(nodata=0)
        rpcs = src.rpcs
        with rasterio.open(blank, "w", **profile) as dst:
            dst.write(np.zeros((1, src.height, src.width), src.dtypes[0]))
            dst.rpcs = rpcs
    grid = grid_like(scene.truth_dsm, chunk=128)
    ds, _ = dsm_from_pair(scene.views[0], blank, grid=grid, params=DSMParams(chunk=128, height_range=scene.height_range))
    out = _compute(ds, tmp_path / "blank")
    assert np.isnan(out["height"].values).all()


def test_missing_and_unreadable_inputs(scene, tmp_path):
    with pytest.raises(TiledsmError, match="nope.tif"):
        dsm_from_pair(scene.views[0], tmp_path / "nope.tif")
    junk = tmp_path / "junk.tif"
    junk.write_bytes(b"junk")
    with pytest.raises(TiledsmError, match="junk.tif"):
        dsm_from_pair(scene.views[0], junk)


def test_heights_above_geoid_match_proj_vgridshift(shared_data, scene):
    """Geoid heights against PROJ's own vertical grid shift with the same grid."""
    from pyproj import Transformer

    from tiledsm.dsm import heights_above_geoid

    gtx = shared_data("shareloc_phr_ventoux", "geoid", "egm96_15.gtx")
    grid = grid_like(scene.truth_dsm, chunk=96)
    h = np.full(grid.shape, 500.0, np.float32)
    ds = xr.Dataset({"height": (("y", "x"), h)}, coords={"y": grid.y, "x": grid.x}).chunk(96)
    ds = ds.rio.write_crs(grid.crs)
    out = heights_above_geoid(ds, gtx)["height"].values
    X, Y = np.meshgrid(grid.x, grid.y)
    lon, lat = Transformer.from_crs(grid.crs, "EPSG:4326", always_xy=True).transform(X, Y)
    # PROJ's vgridshift adds multiplier * N going forward: -1 takes N off
    shift = Transformer.from_pipeline(f"+proj=vgridshift +grids={gtx} +multiplier=-1")
    _, _, H = shift.transform(np.radians(lon), np.radians(lat), h.astype(np.float64), radians=True)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, H, atol=1e-3)
    assert 40 < np.mean(500.0 - out) < 60  # N is about +50 m in Provence


def test_geoid_grid_missing_fails_before_running(scene, tmp_path):
    from tiledsm.dsm import heights_above_geoid
    from tiledsm.errors import InputFileError

    grid = grid_like(scene.truth_dsm, chunk=128)
    ds = xr.Dataset({"height": (("y", "x"), np.zeros(grid.shape, np.float32))}, coords={"y": grid.y, "x": grid.x})
    with pytest.raises(InputFileError, match="nope.gtx"):
        heights_above_geoid(ds.rio.write_crs(grid.crs), tmp_path / "nope.gtx")


@pytest.mark.slow
@pytest.mark.realdata
def test_cli_dsm_s2p_pair_against_s2p(shared_data, tmp_path):
    """The user's command on the real Pleiades pair, on s2p's grid, in chunks of
    256 cells (seams would show), scored here with rasterio alone."""
    from tiledsm.cli import main

    imgs = [str(shared_data("s2p_pair", "input_pair", n)) for n in ("img_01.tif", "img_02.tif")]
    ref_path = shared_data("s2p_pair", "expected_output", "pair", "dsm.tif")
    out = tmp_path / "s2p"
    argv = ["dsm", *imgs, "--out", str(out), "--like", str(ref_path), "--reference", str(ref_path)]
    assert main(argv + ["--chunk", "256", "--workers", "2", "--no-progress"]) == 0
    with rasterio.open(out / "dsm.tif") as a, rasterio.open(ref_path) as b:
        assert a.crs == b.crs and a.transform == b.transform and a.shape == b.shape
        dsm, ref = a.read(1, masked=True).filled(np.nan), b.read(1, masked=True).filled(np.nan)
    both = np.isfinite(ref)
    d = dsm[both] - ref[both]
    completeness = float(np.isfinite(d).mean())
    # issue bounds: NMAD <= 0.5 m, completeness >= 90 % without hole filling
    assert nmad(d) <= 0.5, nmad(d)
    assert completeness >= 0.90, completeness
    assert abs(np.nanmedian(d)) < 0.2
    import json

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["vs_reference"]["nmad"] == pytest.approx(nmad(d), abs=2e-3)  # histogram median: sub-mm bins
    assert (out / "dsm.png").stat().st_size > 10_000


def test_default_grid_in_a_given_crs(scene):
    """--crs without --bounds: the overlap of the views, in that CRS."""
    from pyproj import Transformer

    ds, report = dsm_from_pair(*scene.views, params=DSMParams(crs="EPSG:2154", resolution=1.0, height_range=scene.height_range))
    assert report["grid"]["crs"] == "EPSG:2154" and report["grid"]["resolution"] == 1.0
    assert ds.rio.crs.to_epsg() == 2154
    # the grid covers the truth grid's centre (both views see it)
    truth = grid_like(scene.truth_dsm)
    x, y = Transformer.from_crs(truth.crs, "EPSG:2154", always_xy=True).transform(truth.x.mean(), truth.y.mean())
    assert ds.x.min() < x < ds.x.max() and ds.y.min() < y < ds.y.max()


def test_height_range_without_any_match_gives_nan(scene, tmp_path):
    """A search range far above the ground: every cell is rejected (NaN), no crash."""
    grid = grid_like(scene.truth_dsm, chunk=64).subgrid(448, 576, 448, 576)
    lo = scene.height_range[1] + 2000.0
    ds, _ = dsm_from_pair(*scene.views, grid=grid, params=DSMParams(chunk=64, height_range=(lo, lo + 100.0)))
    out = _compute(ds, tmp_path / "off")
    assert np.isnan(out["height"].values).all()
    assert (tmp_path / "off" / "dsm.zarr").exists()
