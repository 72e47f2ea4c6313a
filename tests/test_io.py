"""Scenes and stores: values against rasterio, cameras against GDAL's RPC
metadata, CRS/transform round trips, atomicity under failure and kill,
resume of chunked stores."""

from __future__ import annotations

import dataclasses
import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import dask
import dask.array as dsa
import numpy as np
import pytest
import rasterio
import xarray as xr
from pyproj import CRS

from tests.conftest import require_shared
from tiledsm.errors import GridError, InputFileError, RPCError, TiledsmError, UnsupportedFormatError
from tiledsm.geometry import RPC
from tiledsm.geometry.grid import GroundGrid
from tiledsm.io.grids import grid_like
from tiledsm.io.cameras import read_rpc
from tiledsm.io import (
    atomic_path,
    create_store,
    open_product,
    open_scene,
    scene_rpc,
    write_blocks,
    write_cog,
    write_geotiff_with_rpc,
    write_resumable,
    write_zarr,
)

REPO = Path(__file__).resolve().parents[1]


def _s2p_rpc() -> RPC:
    with rasterio.open(require_shared("s2p_pair", "input_pair", "img_01.tif")) as src:
        return RPC.from_gdal(src.rpcs.to_gdal())


def _grid(chunk=64) -> GroundGrid:
    return GroundGrid("EPSG:32740", 359668.5, 7652000.0, 0.5, width=300, height=200, chunk=chunk)


def _ramp(grid: GroundGrid) -> xr.DataArray:
    """Analytic field on the grid: h = 0.01 x + 0.02 y (local metres), NaN hole."""
    yy, xx = np.meshgrid(grid.y - grid.y0, grid.x - grid.x0, indexing="ij")
    h = (2300 + 0.01 * xx + 0.02 * yy).astype(np.float32)
    h[10:20, 30:35] = np.nan
    da = xr.DataArray(dsa.from_array(h, chunks=grid.chunk), dims=("y", "x"), coords=grid.coords(), name="height")
    return da.rio.write_crs(grid.crs).rio.write_transform(grid.transform)


# ------------------------------------------------------------------ scenes
def test_open_scene_s2p_lazy_values_and_camera():
    path = require_shared("s2p_pair", "input_pair", "img_01.tif")
    da = open_scene(path, chunks=256)
    assert da.dims == ("y", "x") and da.dtype == np.float32
    assert isinstance(da.data, dsa.Array) and da.chunks == ((256,) * 4, (256,) * 4)
    with rasterio.open(path) as src:
        ref = src.read(1)
        gdal_rpc = RPC.from_gdal(src.rpcs.to_gdal())
    np.testing.assert_array_equal(da.values, ref.astype(np.float32))
    np.testing.assert_array_equal(da.y.values, np.arange(1024) + 0.5)
    np.testing.assert_array_equal(da.x.values, np.arange(1024) + 0.5)
    assert scene_rpc(da) == gdal_rpc
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in da.attrs["rpc"].items())
    assert str(path) in da.attrs["camera_source"]
    assert da.attrs["source_path"] == str(Path(path).resolve())


def test_open_scene_nodata_is_nan():
    path = require_shared("pandora_middlebury_cones", "Cones_LEFT.tif")
    da = open_scene(path, require_camera=False)
    with rasterio.open(path) as src:
        raw = src.read(1)
        assert src.nodata == 255
    v = da.values
    np.testing.assert_array_equal(np.isnan(v), raw == 255)
    np.testing.assert_array_equal(v[raw != 255], raw[raw != 255].astype(np.float32))
    assert "rpc" not in da.attrs


def test_open_scene_crop_uses_array_pixel_coordinates():
    path = require_shared("shareloc_phr_ventoux", "left_image.tif")
    with rasterio.open(path) as src:
        assert src.transform.c == 5000  # crop offset in the geotransform
    da = open_scene(path, require_camera=False)
    np.testing.assert_array_equal(da.x.values, np.arange(500) + 0.5)
    np.testing.assert_array_equal(da.y.values, np.arange(500) + 0.5)
    assert da.rio.crs is None


def test_open_scene_crop_camera_from_geom_sidecar():
    path = require_shared("shareloc_phr_ventoux", "left_image.tif")
    da = open_scene(path)
    assert "geom" in da.attrs["camera_source"].lower()
    rpc = scene_rpc(da)
    # the camera describes the crop: crop pixel (r, c) is full-image pixel
    # (r + 5000, c + 5000) of the .geom RPC
    full = read_rpc(path.with_suffix(".geom"))
    rows, cols = np.array([0.0, 250.0, 499.5]), np.array([0.0, 250.0, 10.0])
    lon, lat = rpc.localize(rows, cols, 480.0)
    lon_f, lat_f = full.localize(rows + 5000, cols + 5000, 480.0)
    np.testing.assert_allclose(lon, lon_f, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lat, lat_f, rtol=0, atol=1e-9)


def test_open_scene_explicit_rpc_object_and_multiband(tmp_path):
    rpc = _s2p_rpc()
    arr = np.arange(3 * 40 * 50, dtype=np.uint16).reshape(3, 40, 50)
    p = write_geotiff_with_rpc(arr, tmp_path / "mb.tif", rpc)
    da = open_scene(p, chunks=16)
    assert da.dims == ("band", "y", "x") and da.chunks[0] == (3,)
    np.testing.assert_array_equal(da.values, arr.astype(np.float32))
    b2 = open_scene(p, band=2, rpc=rpc)
    assert b2.dims == ("y", "x")
    np.testing.assert_array_equal(b2.values, arr[1])
    with pytest.raises(InputFileError, match="no band 4"):
        open_scene(p, band=4)


def test_open_scene_errors(tmp_path):
    with pytest.raises(InputFileError, match="missing.tif: no such file"):
        open_scene(tmp_path / "missing.tif")
    junk = tmp_path / "junk.tif"
    junk.write_text("not an image")
    with pytest.raises(UnsupportedFormatError, match="junk.tif"):
        open_scene(junk)
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8") as dst:
        dst.write(np.zeros((1, 8, 8), np.uint8))
    with pytest.raises(RPCError, match="plain.tif"):
        open_scene(plain)
    da = open_scene(plain, require_camera=False)
    with pytest.raises(RPCError, match="plain.tif: no camera"):
        scene_rpc(da)


# ------------------------------------------------------------------ GeoTIFF with RPC
def test_write_geotiff_with_rpc_round_trip(tmp_path):
    rpc = _s2p_rpc()
    rng = np.random.default_rng(0)
    img = rng.integers(0, 4096, size=(130, 170)).astype(np.uint16)
    img[0, 0] = 0
    p = write_geotiff_with_rpc(dsa.from_array(img, chunks=(32, 64)), tmp_path / "img.tif", rpc, nodata=0)
    with rasterio.open(p) as src:
        assert src.nodata == 0 and src.dtypes[0] == "uint16"
        np.testing.assert_array_equal(src.read(1), img)
        back = RPC.from_gdal(src.rpcs.to_gdal())
    lon = np.linspace(55.647, 55.652, 7)
    lat = np.linspace(-21.233, -21.228, 7)
    for a, b in zip(rpc.project(lon, lat, 2300.0), back.project(lon, lat, 2300.0)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    da = open_scene(p)
    assert np.isnan(da.values[0, 0]) and np.isnan(da.values).sum() == (img == 0).sum()
    assert not list(tmp_path.glob(".*"))  # no temporary left


# ------------------------------------------------------------------ zarr products
def test_write_zarr_round_trip_crs_transform_values_attrs(tmp_path):
    g = _grid()
    da = _ramp(g)
    da.attrs = {"rpc": _s2p_rpc().to_gdal(), "units": "m", "stage": "dsm", "n": 3}
    p = write_zarr(da, tmp_path / "dsm.zarr")
    back = open_product(p)
    assert isinstance(back, xr.DataArray) and back.name == "height"
    assert back.rio.crs == CRS.from_epsg(32740)
    assert back.rio.transform() == g.transform
    np.testing.assert_array_equal(back.values, da.values)  # NaNs at the same places
    assert back.attrs == da.attrs
    assert back.chunks == g.chunks
    assert grid_like(back) == g
    assert scene_rpc(back) == _s2p_rpc()


def test_write_zarr_unnamed_and_dataset_and_modes(tmp_path):
    g = _grid()
    da = _ramp(g).rename(None)
    back = open_product(write_zarr(da, tmp_path / "u.zarr"))
    assert back.name is None and back.rio.crs == CRS.from_epsg(32740)
    ds = xr.Dataset({"h": _ramp(g), "m": (("y", "x"), np.ones(g.shape, np.uint8))}, attrs={"run": "t1"})
    back = open_product(write_zarr(ds, tmp_path / "d.zarr"))
    assert isinstance(back, xr.Dataset) and back.attrs == {"run": "t1"}
    np.testing.assert_array_equal(back["m"].values, 1)
    with pytest.raises(TiledsmError, match="already exists"):
        write_zarr(ds, tmp_path / "d.zarr", mode="w-")
    # mode "w" replaces the old store completely (no stale variables)
    write_zarr(da, tmp_path / "d.zarr")
    assert isinstance(open_product(tmp_path / "d.zarr"), xr.DataArray)
    # a caller-supplied compute (progress bar, client) runs the write
    seen = []
    write_zarr(da, tmp_path / "c.zarr", compute=lambda d: seen.append(dask.compute(d)))
    assert len(seen) == 1
    np.testing.assert_array_equal(open_product(tmp_path / "c.zarr").values, da.values)


def test_open_product_errors(tmp_path):
    with pytest.raises(InputFileError, match="nope.zarr: no such product"):
        open_product(tmp_path / "nope.zarr")
    (tmp_path / "empty.zarr").mkdir()
    with pytest.raises(InputFileError, match="empty.zarr: not a readable zarr"):
        open_product(tmp_path / "empty.zarr")


# ------------------------------------------------------------------ COG
def test_write_cog(tmp_path):
    g = GroundGrid("EPSG:32631", 600_000.0, 4_800_000.0, 1.0, width=600, height=520, chunk=128)
    da = _ramp(g)
    da.attrs["units"] = "m"
    p = write_cog(da, tmp_path / "dsm.tif", blocksize=256)
    with rasterio.open(p) as src:
        assert src.driver == "GTiff"
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert src.crs == CRS.from_epsg(32631) and src.transform == g.transform
        assert np.isnan(src.nodata) and src.block_shapes[0] == (256, 256)
        assert src.overviews(1) == [2, 4]
        assert src.tags()["units"] == "m"
        np.testing.assert_array_equal(src.read(1), da.values)
    assert sorted(os.listdir(tmp_path)) == ["dsm.tif"]
    # a scene in sensor geometry keeps its camera in RPC tags
    scene = xr.DataArray(np.ones((40, 40), np.float32), dims=("y", "x"), attrs={"rpc": _s2p_rpc().to_gdal()})
    with rasterio.open(write_cog(scene, tmp_path / "scene.tif")) as src:
        assert RPC.from_gdal(src.rpcs.to_gdal()) == _s2p_rpc()


def test_write_cog_threads_give_the_same_bytes(tmp_path):
    """Tiles are compressed independently: GDAL's NUM_THREADS changes the
    time, not one byte of the file (heights with noise and holes, so the
    DEFLATE streams are not trivial)."""
    g = GroundGrid("EPSG:32631", 600_000.0, 4_800_000.0, 1.0, width=1100, height=900, chunk=256)
    rng = np.random.default_rng(1)
    z = (2000 + np.cumsum(rng.normal(size=g.shape), axis=1)).astype(np.float32)
    z[rng.random(g.shape) < 0.05] = np.nan
    da = _ramp(g).copy(data=z)
    one = write_cog(da, tmp_path / "one.tif", blocksize=256, threads=1)
    many = write_cog(da, tmp_path / "many.tif", blocksize=256, threads=4)
    assert one.read_bytes() == many.read_bytes()
    with rasterio.open(many) as src:
        np.testing.assert_array_equal(src.read(1), z)


# ------------------------------------------------------------------ atomicity
def test_atomic_path_failure_leaves_nothing_and_keeps_old(tmp_path):
    final = tmp_path / "out.zarr"
    with pytest.raises(RuntimeError):
        with atomic_path(final) as tmp:
            tmp.mkdir()
            (tmp / "half").write_text("x")
            raise RuntimeError("killed mid-write")
    assert os.listdir(tmp_path) == []
    write_zarr(_ramp(_grid()), final)

    def boom(block):
        raise RuntimeError("worker died")

    bad = _ramp(_grid()).copy(data=_ramp(_grid()).data.map_blocks(boom, dtype=np.float32))
    with pytest.raises(RuntimeError, match="worker died"):
        write_zarr(bad, final)
    assert os.listdir(tmp_path) == ["out.zarr"]  # old product intact, no temporary
    np.testing.assert_array_equal(open_product(final).values, _ramp(_grid()).values)
    with pytest.raises(TiledsmError, match="produced nothing"):
        with atomic_path(tmp_path / "x.tif"):
            pass


def test_killed_process_leaves_no_final_name(tmp_path):
    script = textwrap.dedent(
        f"""
        import os, numpy as np, dask, dask.array as da, xarray as xr
        from tiledsm.io import write_zarr, write_cog
        dask.config.set(scheduler="synchronous")
        n = [0]
        def die(b):
            n[0] += 1
            if n[0] == 3:
                os._exit(9)   # hard kill: no cleanup handlers run
            return b
        x = da.zeros((256, 256), chunks=64, dtype="float32").map_blocks(die, dtype="float32")
        arr = xr.DataArray(x, dims=("y", "x"), name="h")
        write_zarr(arr, {str(tmp_path / "p.zarr")!r})
        """
    )
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, timeout=120)
    assert r.returncode == 9, r.stderr.decode()[-2000:]
    assert not (tmp_path / "p.zarr").exists()
    left = os.listdir(tmp_path)
    assert all(n.startswith(".p.zarr.tmp-") for n in left)  # only a hidden temporary


# ------------------------------------------------------------------ resumable stores
def _flaky(calls, fail_call=None):
    """Record each block's location; the ``fail_call``-th call (1-based)
    raises. Failing by position, not by block, keeps the test independent of
    the order dask picks (task keys are random): blocks run before it exist."""

    def f(block, block_info=None):
        loc = tuple(block_info[0]["chunk-location"])
        calls.append(loc)
        if len(calls) == fail_call:
            raise RuntimeError(f"task {loc} failed")
        return block

    return f


def test_store_resume_skips_finished_blocks(tmp_path):
    g = _grid(chunk=64)  # 4 x 5 blocks
    truth = _ramp(g)
    store = create_store(tmp_path / "dsm.zarr", g, {"height": "float32"}, attrs={"stage": "dsm"})
    assert store.numblocks == (4, 5) and len(store.pending()) == 20
    assert pickle.loads(pickle.dumps(store)) == store
    calls: list = []
    data = truth.data.map_blocks(_flaky(calls, fail_call=6), dtype=np.float32)
    with dask.config.set(scheduler="synchronous"), pytest.raises(RuntimeError, match="failed"):
        write_blocks(data, store)
    assert not (tmp_path / "dsm.zarr").exists() and (tmp_path / "dsm.zarr.partial").exists()
    done_before = set(map(tuple, np.argwhere(store.done())))
    assert calls[-1] not in done_before and 1 <= len(done_before) <= 5
    assert done_before <= set(calls[:-1])
    with pytest.raises(InputFileError, match="no such product.*unfinished store"):
        open_product(tmp_path / "dsm.zarr")
    with pytest.raises(InputFileError, match="incomplete store"):
        open_product(store.partial_path)
    with pytest.raises(TiledsmError, match="pending"):
        store.finalize()
    # resume: a fresh create_store reuses the partial store; only pending blocks run
    store2 = create_store(tmp_path / "dsm.zarr", g, {"height": "float32"}, attrs={"stage": "dsm"})
    calls2: list = []
    data2 = truth.data.map_blocks(_flaky(calls2), dtype=np.float32)
    ran = []
    with dask.config.set(scheduler="synchronous"):
        n = write_blocks(data2, store2, compute=lambda d: ran.append(d.compute()))
    assert ran == [n]
    assert n == 20 - len(done_before)
    assert set(calls2) == {(i, j) for i in range(4) for j in range(5)} - done_before
    out = open_product(tmp_path / "dsm.zarr")
    assert isinstance(out, xr.Dataset) and out.attrs == {"stage": "dsm"}
    np.testing.assert_array_equal(out["height"].values, truth.values)
    assert out.rio.crs == CRS.from_epsg(32740) and out["height"].rio.transform() == g.transform
    assert sorted(os.listdir(tmp_path)) == ["dsm.zarr"]
    # a finished store is returned as is: nothing to do
    store3 = create_store(tmp_path / "dsm.zarr", g, {"height": "float32"})
    assert store3.is_complete and write_blocks(data2, store3) == 0


def test_store_block_writes_from_tasks_and_multivariable(tmp_path):
    g = _grid(chunk=50)
    store = create_store(tmp_path / "s.zarr", g, {"h": "float32", "n": "uint8"})
    # a stage writing blocks itself (e.g. inside its own dask tasks), in any order
    for (i, j), (r0, r1, c0, c1) in reversed(list(g.blocks())):
        store.write_block(i, j, {"h": np.full((r1 - r0, c1 - c0), i * 10 + j, np.float32),
                                 "n": np.full((r1 - r0, c1 - c0), 7, np.uint8)})
    store.finalize()
    out = open_product(tmp_path / "s.zarr")
    assert out["h"].values[199, 299] == 35 and out["h"].values[0, 60] == 1
    assert out["n"].dtype == np.uint8 and np.all(out["n"].values == 7)
    # two variables from one kernel: the kernel runs once per block
    calls: list = []
    h = _ramp(g).data.map_blocks(_flaky(calls), dtype=np.float32)
    s2 = create_store(tmp_path / "t.zarr", g, {"h": "float32", "n": "uint8"})
    assert write_blocks({"h": h, "n": (h > 2300).astype(np.uint8)}, s2) == 24
    assert sorted(calls) == sorted(ij for ij, _ in g.blocks())
    out = open_product(tmp_path / "t.zarr")
    np.testing.assert_array_equal(out["n"].values, (_ramp(g).values > 2300).astype(np.uint8))


def test_store_blocks_are_compressed_with_the_store_codec(tmp_path):
    import zarr

    from tiledsm.io.codecs import store_compressors

    g = _grid(chunk=100)
    truth = _ramp(g)
    s = create_store(tmp_path / "c.zarr", g, {"height": "float32", "n": "uint8"})
    for (i, j), (r0, r1, c0, c1) in g.blocks():
        s.write_block(i, j, {"height": truth.values[r0:r1, c0:c1], "n": np.full((r1 - r0, c1 - c0), 3, np.uint8)})
    s.finalize()
    group = zarr.open_group(str(tmp_path / "c.zarr"), mode="r")
    want = store_compressors()[0]
    for name in ("height", "n"):
        (got,) = group[name].compressors
        assert (type(got), got.cname, got.shuffle, got.clevel) == (type(want), want.cname, want.shuffle, want.clevel)
    np.testing.assert_array_equal(open_product(tmp_path / "c.zarr")["height"].values, truth.values)


def test_store_unwritten_cells_are_fill_and_incompatible_partial_discarded(tmp_path):
    g = _grid(chunk=100)
    s = create_store(tmp_path / "a.zarr", g)
    s.write_block(0, 0, np.zeros((100, 100), np.float32))
    assert s.blocks_done([(0, 0)]) and not s.blocks_done([(0, 0), (0, 1)]) and s.blocks_done([])
    assert s.pending()[0] == (0, 1) and not s.done()[0, 1]
    part = open_product(s.partial_path, allow_incomplete=True)["data"].values
    assert np.all(part[:100, :100] == 0) and np.all(np.isnan(part[100:])) and np.all(np.isnan(part[:, 100:]))
    # other chunking: the partial store is not reusable, it is rebuilt
    s2 = create_store(tmp_path / "a.zarr", dataclasses.replace(g, chunk=50))
    assert len(s2.pending()) == 4 * 6


def test_store_with_band_template_and_chunk_mismatch(tmp_path):
    g = _grid(chunk=100)
    tmpl = xr.DataArray(
        dsa.zeros((3,) + g.shape, chunks=(1, 100, 100), dtype=np.float32),
        dims=("band", "y", "x"), coords={"band": [1, 2, 3], **g.coords()},
    ).rio.write_crs(g.crs)
    store = create_store(tmp_path / "o.zarr", tmpl, ("ortho",))
    assert store.shape == (3, 200, 300)
    with pytest.raises(GridError, match="differ from the store's blocks"):
        write_blocks(dsa.ones((3, 200, 300), chunks=(3, 64, 64)), store)
    write_blocks(dsa.ones((3, 200, 300), chunks=(1, 100, 100)) * np.arange(3)[:, None, None], store)
    out = open_product(tmp_path / "o.zarr")
    np.testing.assert_array_equal(out["ortho"].values[:, 5, 5], [0, 1, 2])
    assert out.rio.crs == CRS.from_epsg(32740)


def test_write_resumable_round_trip_and_resume(tmp_path):
    g = _grid(chunk=64)
    da = _ramp(g)
    da.attrs = {"units": "m", "rpc": _s2p_rpc().to_gdal()}
    back = open_product(write_resumable(da, tmp_path / "r.zarr"))
    assert isinstance(back, xr.DataArray) and back.name == "height" and back.attrs == da.attrs
    assert back.rio.crs == CRS.from_epsg(32740) and back.rio.transform() == g.transform
    np.testing.assert_array_equal(back.values, da.values)
    # a Dataset whose first run dies in one block: the re-run computes only that block
    calls: list = []
    h = da.data.map_blocks(_flaky(calls, fail_call=4), dtype=np.float32)
    ds = xr.Dataset(
        {"height": da.copy(data=h), "valid": da.copy(data=dsa.isfinite(h).astype(np.uint8))},
        attrs={"stage": "dsm"},
    )
    ds["valid"].attrs = {"flag": "1 = height present"}
    with dask.config.set(scheduler="synchronous"), pytest.raises(RuntimeError, match="failed"):
        write_resumable(ds, tmp_path / "ds.zarr")
    assert not (tmp_path / "ds.zarr").exists()
    failed = calls[-1]
    calls.clear()
    h2 = da.data.map_blocks(_flaky(calls), dtype=np.float32)
    ds2 = ds.copy(data={"height": h2, "valid": dsa.isfinite(h2).astype(np.uint8)})
    with dask.config.set(scheduler="synchronous"):
        write_resumable(ds2, tmp_path / "ds.zarr")
    n_done_first = 20 - len(set(calls))
    assert failed in calls and 1 <= n_done_first <= 3
    out = open_product(tmp_path / "ds.zarr")
    assert out.attrs == {"stage": "dsm"} and out["valid"].attrs == {"flag": "1 = height present"}
    np.testing.assert_array_equal(out["height"].values, da.values)
    np.testing.assert_array_equal(out["valid"].values, np.isfinite(da.values).astype(np.uint8))


def test_gdal_block_cache_is_capped_unless_the_user_set_it():
    """GDAL's default cache (5 % of the machine's memory per process) grew every
    worker of a 16384² run to 2.1 GB; tiledsm caps it, a user's value wins."""
    import subprocess
    import sys

    code = "import os, tiledsm; print(os.environ['GDAL_CACHEMAX'])"
    env = {k: v for k, v in os.environ.items() if k != "GDAL_CACHEMAX"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "64"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "GDAL_CACHEMAX": "512"}, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "512"
    # and GDAL itself sees the cap (its config falls back to the environment); what the cap
    # saves in memory is measured in benchmarks (RSS deltas differ between machines)
    cfg = ("import tiledsm, rasterio\n"
           "from rasterio.env import get_gdal_config\n"
           "with rasterio.Env():\n"
           "    print(get_gdal_config('GDAL_CACHEMAX'))\n")
    out = subprocess.run([sys.executable, "-c", cfg], env=env, capture_output=True, text=True, check=True)
    assert int(out.stdout) == 64 * 2**20  # GDAL reports the cache size in bytes


def test_open_store_array_opens_once_and_again_when_remade(tmp_path):
    """The same zarr array object while its metadata file stays; a store
    removed and made anew (another shape) is opened afresh and read right;
    a missing array raises zarr's own error."""
    import shutil

    import zarr

    from tiledsm.io import open_store_array

    store = tmp_path / "s.zarr"
    zarr.create_array(store=str(store), name="h", shape=(4, 4), chunks=(2, 2), dtype="float32", fill_value=0)
    a = open_store_array(store, "h", mode="r+")
    a[0:2, 0:2] = 7.0
    assert open_store_array(store, "h", mode="r+") is a
    assert open_store_array(store, "h", mode="r") is not a  # one per mode
    assert float(np.asarray(open_store_array(store, "h", mode="r")[0, 0])) == 7.0
    shutil.rmtree(store)
    zarr.create_array(store=str(store), name="h", shape=(6, 3), chunks=(3, 3), dtype="float32", fill_value=1)
    b = open_store_array(store, "h", mode="r")
    assert b is not a and b.shape == (6, 3)
    assert np.asarray(b[...]).tolist() == np.ones((6, 3)).tolist()
    with pytest.raises(Exception) as err:
        open_store_array(store, "missing", mode="r")
    assert "missing" in str(err.value)
