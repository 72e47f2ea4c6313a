"""The bad-input matrix: every case a user can get wrong, through the CLI.

Each case runs ``python -m tiledsm ...`` (the way users run it) and must
end with exit code 2, exactly one ``tiledsm COMMAND: error: ...`` line on
stderr naming the file or the option/field at fault, no traceback, and no
finished-looking product in ``--out`` (no ``metrics.json``, DSM, COG or
report).

The inputs are made once per module from a small synthetic scene (its two
views carry RPC tags, its truth DSM a CRS) and altered copies of them.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import rasterio

from tiledsm.synth import make_scene

PRODUCTS = ("metrics.json", "dsm.zarr", "dsm.tif", "dh.zarr", "dh.tif", "report.html", "recipe.resolved.yaml",
            "ortho.zarr", "ortho.json", "orient.json")


@pytest.fixture(scope="module")
def k(tmp_path_factory):
    """The scene and the altered inputs, by name."""
    root = tmp_path_factory.mktemp("bad")
    s = make_scene(root / "scene", size=160, gsd=0.5, bh=0.4, seed=11, views=2)
    v0, v1, truth = Path(s.views[0]), Path(s.views[1]), Path(s.truth_dsm)
    f = {"v0": v0, "v1": v1, "truth": truth, "root": root}

    data = v0.read_bytes()
    (root / "truncated.tif").write_bytes(data[: len(data) // 3])
    f["truncated"] = root / "truncated.tif"

    with rasterio.open(v0) as src:
        profile, img, rpcs = src.profile, src.read(1), src.rpcs
    plain = {**profile}
    with rasterio.open(root / "no_rpc.tif", "w", **plain) as dst:
        dst.write(img, 1)
    f["no_rpc"] = root / "no_rpc.tif"

    def with_rpc(name, array, rpc, **extra):
        prof = {**profile, **extra, "count": array.shape[0] if array.ndim == 3 else 1}
        with rasterio.open(root / name, "w", **prof) as dst:
            if array.ndim == 3:
                dst.write(array)
            else:
                dst.write(array, 1)
            dst.rpcs = rpc
        return root / name

    broken = rasterio.rpc.RPC(**{**rpcs.to_dict(), "line_scale": 0.0})
    f["zero_scale"] = with_rpc("zero_scale.tif", img, broken)
    nodata = np.zeros_like(img)
    f["all_nodata"] = with_rpc("all_nodata.tif", nodata, rpcs, nodata=0)
    f["one_px"] = with_rpc("one_px.tif", img[:1, :1], rpcs, width=1, height=1)
    lying = rasterio.rpc.RPC(**{**rpcs.to_dict(), "line_off": rpcs.line_off + 50000.0, "samp_off": rpcs.samp_off + 50000.0})
    f["rpc_elsewhere"] = with_rpc("rpc_elsewhere.tif", img, lying)
    south = rasterio.rpc.RPC(**{**rpcs.to_dict(), "lat_off": -rpcs.lat_off})
    f["other_hemisphere"] = with_rpc("other_hemisphere.tif", img, south)
    shutil.copy(v0, root / "truncated_rpc.tif")
    with rasterio.open(root / "truncated_rpc.tif", "r+") as dst:  # 10 of 20 numbers, as a user's edit may leave
        dst.update_tags(ns="RPC", LINE_NUM_COEFF=" ".join(dst.tags(ns="RPC")["LINE_NUM_COEFF"].split()[:10]))
    f["truncated_rpc"] = root / "truncated_rpc.tif"
    away = rasterio.rpc.RPC(**{**rpcs.to_dict(), "long_off": rpcs.long_off + 1.0})
    f["ground_elsewhere"] = with_rpc("ground_elsewhere.tif", img, away)  # a scene 80 km east

    with rasterio.open(truth) as src:
        tprof, tdem = src.profile, src.read(1)
    no_crs = {**tprof}
    no_crs.pop("crs", None)
    with rasterio.open(root / "dsm_no_crs.tif", "w", **no_crs) as dst:
        dst.write(tdem, 1)
    f["dsm_no_crs"] = root / "dsm_no_crs.tif"
    far = {**tprof, "transform": rasterio.transform.Affine(0.5, 0, 100000.0, 0, -0.5, 1000000.0)}
    with rasterio.open(root / "dsm_far.tif", "w", **far) as dst:
        dst.write(tdem, 1)
    f["dsm_far"] = root / "dsm_far.tif"

    (root / "empty.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    f["empty_mask"] = root / "empty.geojson"
    (root / "broken.geojson").write_text("{not json")
    f["broken_mask"] = root / "broken.geojson"
    far_poly = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": {
        "type": "Polygon", "coordinates": [[[10.0, 10.0], [10.001, 10.0], [10.001, 10.001], [10.0, 10.001], [10.0, 10.0]]]}}]}
    (root / "far.geojson").write_text(json.dumps(far_poly))
    f["far_mask"] = root / "far.geojson"
    metres = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": {
        "type": "Polygon", "coordinates": [[[500000.0, 4890000.0], [500040.0, 4890000.0], [500040.0, 4890040.0],
                                            [500000.0, 4890000.0]]]}}]}  # UTM metres, "crs" member dropped
    (root / "metres_no_crs.geojson").write_text(json.dumps(metres))
    f["metres_mask"] = root / "metres_no_crs.geojson"
    from rasterio.warp import calculate_default_transform, reproject

    gt, gw, gh = calculate_default_transform(tprof["crs"], "EPSG:4326", tdem.shape[1], tdem.shape[0],
                                             *rasterio.transform.array_bounds(*tdem.shape, tprof["transform"]))
    geo = np.zeros((gh, gw), np.float32)
    reproject(tdem, geo, src_transform=tprof["transform"], src_crs=tprof["crs"], dst_transform=gt, dst_crs="EPSG:4326")
    with rasterio.open(root / "dsm_geographic.tif", "w", **{**tprof, "crs": "EPSG:4326", "transform": gt,
                                                            "width": gw, "height": gh}) as dst:
        dst.write(geo, 1)
    f["dsm_geographic"] = root / "dsm_geographic.tif"
    (root / "not_a_raster.tif").write_text("hello")
    f["text_tif"] = root / "not_a_raster.tif"
    (root / "a_folder").mkdir()
    f["folder"] = root / "a_folder"
    (root / "a_file").write_text("x")
    shutil.copy(v0, root / "earlier_sr.tif")  # an output an earlier `tiledsm sr` wrote
    f["earlier_sr"] = root / "earlier_sr.tif"
    f["file"] = root / "a_file"

    # a geoid grid that covers another part of the world only
    geoid = np.full((10, 10), 40.0, np.float32)
    with rasterio.open(root / "geoid_elsewhere.gtx", "w", driver="GTX", width=10, height=10, count=1, dtype="float32",
                       crs="EPSG:4326", transform=rasterio.transform.from_origin(100.0, -30.0, 0.25, 0.25)) as dst:
        dst.write(geoid, 1)
    f["geoid_elsewhere"] = root / "geoid_elsewhere.gtx"

    (root / "gcps_bad_columns.csv").write_text("name,image,x,y\nA,view_0.tif,1,2\n")
    f["gcps_bad_columns"] = root / "gcps_bad_columns.csv"
    (root / "gcps_dup.csv").write_text(
        "id,image,lon,lat,h,row,col\nA,view_0.tif,3.0,45.0,300,10,10\nA,view_0.tif,3.0,45.0,300,12,12\n")
    f["gcps_dup"] = root / "gcps_dup.csv"

    from tiledsm.geometry import RPC

    cam0, cam1 = RPC.from_gdal(rpcs.to_dict()), RPC.from_gdal(rasterio.open(v1).rpcs.to_dict())
    rc = np.array([[40.0, 40.0], [120.0, 50.0], [60.0, 130.0]])
    lon, lat = cam0.localize(rc[:, 0], rc[:, 1], np.full(3, cam0.height_off))
    r1, c1 = cam1.project(lon, lat, np.full(3, cam0.height_off))

    def gcp_file(name, dlon=(0.0, 0.0, 0.0), dlat=(0.0, 0.0, 0.0)):
        rows = ["id,image,lon,lat,h,row,col"]
        for k in range(3):
            for image, row, col in (("view_0.tif", rc[k, 0], rc[k, 1]), ("view_1.tif", r1[k], c1[k])):
                rows.append(f"G{k},{image},{lon[k] + dlon[k]:.9f},{lat[k] + dlat[k]:.9f},{cam0.height_off:.3f},"
                            f"{row:.3f},{col:.3f}")
        (root / name).write_text("\n".join(rows) + "\n")
        return root / name

    f["gcps_elsewhere"] = gcp_file("gcps_elsewhere.csv", dlon=(10.0, 10.0, 10.0))  # the case: 3e5 px off
    m = 1 / 111_000  # about a metre, in degrees: ground 30 m off, each GCP another way
    f["gcps_inconsistent"] = gcp_file("gcps_inconsistent.csv", dlon=(30 * m, -30 * m, 0.0), dlat=(0.0, 0.0, 30 * m))

    def recipe(name: str, text: str) -> Path:
        (root / name).write_text(text)
        return root / name

    images = f"  images: [{v0}, {v1}]\n"
    f["r_windw"] = recipe("windw.yaml", f"pipeline: dsm\ninput:\n{images}match: {{params: {{windw: 5}}}}\n")
    f["r_window_even"] = recipe("window_even.yaml", f"pipeline: dsm\ninput:\n{images}match: {{params: {{window: 4}}}}\n")
    f["r_p1_above_p2"] = recipe("p1_above_p2.yaml", f"pipeline: dsm\ninput:\n{images}match: {{params: {{P1: 3}}}}\n")
    f["r_field"] = recipe("field.yaml", f"pipeline: dsm\ninput:\n{images}grid: {{chunck: 64}}\n")
    f["r_pipeline"] = recipe("pipeline.yaml", f"pipeline: dsn\ninput:\n{images}")
    f["r_pipeline_list"] = recipe("pipeline_list.yaml", f"pipeline: [dsm]\ninput:\n{images}")
    f["r_scale"] = recipe("scale.yaml", f"pipeline: sr_dsm\ninput:\n{images}sr: {{scale: 3}}\n")
    f["r_missing"] = recipe("missing_img.yaml", f"pipeline: dsm\ninput:\n  images: [{root / 'nope.tif'}, {v1}]\n")
    return f


@dataclass(frozen=True)
class Case:
    id: str
    argv: Callable[[dict, Path], list[str]]
    names: Callable[[dict], list[str]]  # each must appear in the error line


def dsm(*extra):
    return lambda f, out: ["dsm", str(f["v0"]), str(f["v1"]), "--out", str(out), *[str(f.get(e, e)) for e in extra]]


def dsm_with(first):
    return lambda f, out: ["dsm", str(f[first]), str(f["v1"]), "--out", str(out)]


CASES = [
    # --- dsm: files
    Case("dsm-missing-image", lambda f, out: ["dsm", str(f["root"] / "nope.tif"), str(f["v1"]), "--out", str(out)],
         lambda f: ["nope.tif"]),
    Case("dsm-truncated-tiff", dsm_with("truncated"), lambda f: ["truncated.tif"]),
    Case("dsm-text-as-tiff", dsm_with("text_tif"), lambda f: ["not_a_raster.tif"]),
    Case("dsm-image-is-folder", dsm_with("folder"), lambda f: ["a_folder"]),
    Case("dsm-no-rpc", dsm_with("no_rpc"), lambda f: ["no_rpc.tif"]),
    Case("dsm-rpc-zero-scale", dsm_with("zero_scale"), lambda f: ["zero_scale.tif"]),
    Case("dsm-all-nodata", dsm_with("all_nodata"), lambda f: ["all_nodata.tif"]),
    Case("dsm-one-pixel", dsm_with("one_px"), lambda f: ["one_px.tif"]),
    Case("dsm-rpc-lies-about-position", dsm_with("rpc_elsewhere"), lambda f: ["rpc_elsewhere.tif"]),
    Case("dsm-rpc-truncated-coefficients", dsm_with("truncated_rpc"), lambda f: ["truncated_rpc.tif", "line_num", "truncated"]),
    Case("dsm-rpc-offsets-of-another-image", dsm_with("rpc_elsewhere"), lambda f: ["rpc_elsewhere.tif", "LINE_OFF"]),
    Case("dsm-other-hemisphere", lambda f, out: ["dsm", str(f["v0"]), str(f["other_hemisphere"]), "--out", str(out)],
         lambda f: [f["v0"].name, "other_hemisphere.tif", "no common ground"]),
    Case("dsm-same-image-twice", lambda f, out: ["dsm", str(f["v0"]), str(f["v0"]), "--out", str(out)],
         lambda f: [f["v0"].name]),
    # --- dsm: options
    Case("dsm-resolution-zero", dsm("--resolution", "0"), lambda f: ["--resolution"]),
    Case("dsm-resolution-negative", dsm("--resolution", "-1"), lambda f: ["--resolution"]),
    Case("dsm-resolution-huge", dsm("--resolution", "1e6"), lambda f: ["--resolution"]),
    Case("dsm-chunk-zero", dsm("--chunk", "0"), lambda f: ["--chunk"]),
    Case("dsm-chunk-odd", dsm("--chunk", "101"), lambda f: ["--chunk", "must be even", "101"]),
    Case("dsm-crs-unknown", dsm("--crs", "EPSG:99999"), lambda f: ["--crs", "EPSG:99999"]),
    Case("dsm-out-is-a-file", lambda f, out: ["dsm", str(f["v0"]), str(f["v1"]), "--out", str(f["file"])],
         lambda f: ["a_file", "--out"]),
    Case("dsm-bounds-outside", dsm("--crs", "EPSG:32631", "--resolution", "0.5", "--bounds", "100", "100", "200", "200"),
         lambda f: ["--bounds"]),
    Case("dsm-like-far-away", dsm("--like", "dsm_far"), lambda f: ["--like"]),
    # a geographic raster is compared on its own grid, but a DSM is made on a projected one
    Case("dsm-like-geographic", dsm("--like", "dsm_geographic"), lambda f: ["dsm_geographic.tif", "--like", "geographic"]),
    Case("dsm-like-not-a-raster", dsm("--like", "text_tif"), lambda f: ["not_a_raster.tif", "--like"]),
    Case("dsm-height-range-inverted", dsm("--height-range", "400", "300"), lambda f: ["--height-range"]),
    Case("dsm-reference-missing", dsm("--reference", "nope_ref.tif"), lambda f: ["nope_ref.tif", "--reference"]),
    Case("dsm-reference-far-away", dsm("--reference", "dsm_far"), lambda f: ["dsm_far.tif", "--reference"]),
    Case("dsm-geoid-missing", dsm("--geoid", "nope.gtx"), lambda f: ["nope.gtx"]),
    Case("dsm-geoid-elsewhere", dsm("--geoid", "geoid_elsewhere"), lambda f: ["geoid_elsewhere.gtx"]),
    Case("dsm-workers-zero", dsm("--workers", "0"), lambda f: ["--workers"]),
    Case("dsm-device-unknown", dsm("--device", "gpu7"), lambda f: ["--device", "gpu7", "cuda, cuda:N"]),
    # a CUDA device that this machine lacks (cuda:64: no machine has that many)
    Case("dsm-device-absent", dsm("--device", "cuda:64"), lambda f: ["--device", "cuda:64"]),
    Case("dsm-memory-per-worker-not-a-size", dsm("--memory-per-worker", "lots"), lambda f: ["--memory-per-worker", "lots"]),
    # --- sr
    Case("sr-missing-input", lambda f, out: ["sr", str(f["root"] / "nope.tif"), str(out)], lambda f: ["nope.tif"]),
    Case("sr-scale-without-weights", lambda f, out: ["sr", str(f["v0"]), str(out), "--model", "srcnn", "--scale", "3"],
         lambda f: ["--scale"]),
    Case("sr-truncated-input", lambda f, out: ["sr", str(f["truncated"]), str(out)], lambda f: ["truncated.tif"]),
    # the command's older form named the output file: OUT is now the run folder
    Case("sr-output-is-a-file-name", lambda f, out: ["sr", str(f["v0"]), str(f["earlier_sr"]), "--model", "bicubic"],
         lambda f: ["earlier_sr.tif", "OUT", "run folder", "sr.tif"]),
    # --- compare
    Case("compare-missing", lambda f, out: ["compare", str(f["truth"]), str(f["root"] / "nope.tif"), "--out", str(out)],
         lambda f: ["nope.tif"]),
    Case("compare-no-overlap", lambda f, out: ["compare", str(f["truth"]), str(f["dsm_far"]), "--out", str(out)],
         lambda f: ["dsm_far.tif"]),
    Case("compare-no-crs", lambda f, out: ["compare", str(f["truth"]), str(f["dsm_no_crs"]), "--out", str(out)],
         lambda f: ["dsm_no_crs.tif"]),
    Case("compare-mask-empty", lambda f, out: ["compare", str(f["truth"]), str(f["truth"]), "--out", str(out),
                                              "--stable-mask", str(f["empty_mask"])], lambda f: ["empty.geojson"]),
    Case("compare-mask-broken", lambda f, out: ["compare", str(f["truth"]), str(f["truth"]), "--out", str(out),
                                               "--stable-mask", str(f["broken_mask"])], lambda f: ["broken.geojson"]),
    Case("compare-mask-elsewhere", lambda f, out: ["compare", str(f["truth"]), str(f["truth"]), "--out", str(out),
                                                  "--stable-mask", str(f["far_mask"])], lambda f: ["far.geojson"]),
    Case("compare-mask-metres-without-crs", lambda f, out: ["compare", str(f["truth"]), str(f["truth"]), "--out", str(out),
                                                           "--stable-mask", str(f["metres_mask"])],
         lambda f: ["metres_no_crs.geojson", "not longitude/latitude", '"crs"']),
    # --- run (recipes)
    Case("run-misspelled-match-param", lambda f, out: ["run", str(f["r_windw"]), "--out", str(out)], lambda f: ["windw"]),
    # the matching parameters' own checks name the field path (pydantic's location)
    Case("run-even-match-window", lambda f, out: ["run", str(f["r_window_even"]), "--out", str(out)],
         lambda f: ["window_even.yaml", "match.params.window", "must be odd", "4"]),
    Case("run-p1-above-default-p2", lambda f, out: ["run", str(f["r_p1_above_p2"]), "--out", str(out)],
         lambda f: ["match.params.P2", ">= P1 (3.0)", "2.0"]),
    Case("run-unknown-field", lambda f, out: ["run", str(f["r_field"]), "--out", str(out)], lambda f: ["chunck"]),
    Case("run-unknown-pipeline", lambda f, out: ["run", str(f["r_pipeline"]), "--out", str(out)], lambda f: ["dsn"]),
    Case("run-pipeline-is-a-list", lambda f, out: ["run", str(f["r_pipeline_list"]), "--out", str(out)],
         lambda f: ["pipeline_list.yaml", "pipeline:", "['dsm']", "a list"]),
    Case("run-sr-scale-without-weights", lambda f, out: ["run", str(f["r_scale"]), "--out", str(out)], lambda f: ["sr.scale"]),
    Case("run-recipe-is-folder", lambda f, out: ["run", str(f["folder"]), "--out", str(out)], lambda f: ["a_folder"]),
    Case("run-recipe-image-missing", lambda f, out: ["run", str(f["r_missing"]), "--out", str(out)], lambda f: ["nope.tif"]),
    # --- ortho
    Case("ortho-dsm-missing", lambda f, out: ["ortho", str(f["v0"]), "--dsm", str(f["root"] / "nope.tif"), "--out", str(out)],
         lambda f: ["nope.tif"]),
    Case("ortho-unknown-kernel", lambda f, out: ["ortho", str(f["v0"]), "--dsm", str(f["truth"]), "--out", str(out),
                                                "--kernel", "lanczos"], lambda f: ["lanczos"]),
    Case("ortho-dsm-elsewhere", lambda f, out: ["ortho", str(f["v0"]), "--dsm", str(f["dsm_far"]), "--out", str(out)],
         lambda f: ["dsm_far.tif"]),
    Case("ortho-truncated-image", lambda f, out: ["ortho", str(f["truncated"]), "--dsm", str(f["truth"]), "--out", str(out)],
         lambda f: ["truncated.tif", "IMAGE"]),
    Case("ortho-camera-file-missing", lambda f, out: ["ortho", str(f["v0"]), "--dsm", str(f["truth"]), "--out", str(out),
                                                     "--camera", str(f["root"] / "nope.yaml")], lambda f: ["nope.yaml", "--camera"]),
    Case("ortho-image-without-camera", lambda f, out: ["ortho", str(f["no_rpc"]), "--dsm", str(f["truth"]), "--out", str(out)],
         lambda f: ["no_rpc.tif"]),
    # --- orient
    Case("orient-gcps-missing", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--gcps", str(f["root"] / "nope.csv"),
                                               "--out", str(out)], lambda f: ["nope.csv"]),
    Case("orient-gcps-wrong-columns", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--gcps",
                                                     str(f["gcps_bad_columns"]), "--out", str(out)],
         lambda f: ["gcps_bad_columns.csv"]),
    Case("orient-gcps-duplicate-ids", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--gcps", str(f["gcps_dup"]),
                                                     "--out", str(out)], lambda f: ["gcps_dup.csv"]),
    Case("orient-no-common-ground", lambda f, out: ["orient", str(f["v0"]), str(f["ground_elsewhere"]), "--out", str(out)],
         lambda f: ["ground_elsewhere.tif", "no common ground"]),
    Case("orient-gcps-elsewhere", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--gcps", str(f["gcps_elsewhere"]),
                                                 "--out", str(out)], lambda f: ["gcps_elsewhere.csv", "--gcps"]),
    Case("orient-gcps-all-rejected", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--gcps",
                                                    str(f["gcps_inconsistent"]), "--out", str(out)],
         lambda f: ["gcps_inconsistent.csv", "--gcps", "rejected every GCP"]),
    Case("orient-other-hemisphere", lambda f, out: ["orient", str(f["v0"]), str(f["other_hemisphere"]), "--out", str(out)],
         lambda f: [f["v0"].name, "other_hemisphere.tif", "no common ground"]),
    Case("orient-rpc-truncated-coefficients", lambda f, out: ["orient", str(f["v0"]), str(f["truncated_rpc"]),
                                                             "--out", str(out)], lambda f: ["truncated_rpc.tif", "line_num"]),
    Case("orient-truncated-image", lambda f, out: ["orient", str(f["v0"]), str(f["truncated"]), "--out", str(out)],
         lambda f: ["truncated.tif"]),
    Case("orient-geoid-without-dem", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--geoid",
                                                    str(f["geoid_elsewhere"]), "--out", str(out)], lambda f: ["--geoid"]),
    Case("orient-dem-missing", lambda f, out: ["orient", str(f["v0"]), str(f["v1"]), "--dem", str(f["root"] / "nope_dem.tif"),
                                              "--out", str(out)], lambda f: ["nope_dem.tif", "--dem"]),
    Case("orient-image-without-rpc", lambda f, out: ["orient", str(f["no_rpc"]), str(f["v1"]), "--out", str(out)],
         lambda f: ["no_rpc.tif"]),
    # --- info, synth
    Case("info-missing", lambda f, out: ["info", str(f["root"] / "nope.tif")], lambda f: ["nope.tif"]),
    Case("info-folder", lambda f, out: ["info", str(f["folder"])], lambda f: ["a_folder"]),
    Case("synth-size-zero", lambda f, out: ["synth", str(out / "s"), "--size", "0"], lambda f: ["--size"]),
    Case("synth-out-is-a-file", lambda f, out: ["synth", str(f["file"]), "--size", "64"], lambda f: ["a_file"]),
    Case("synth-gsd-negative", lambda f, out: ["synth", str(out / "s"), "--size", "64", "--gsd", "-1"], lambda f: ["--gsd"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_clear_line(k, case, tmp_path):
    out = tmp_path / "out"
    argv = case.argv(k, out)
    r = subprocess.run([sys.executable, "-m", "tiledsm", *argv], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    command = argv[0]
    prefix = f"tiledsm {command}: error:"
    assert r.returncode == 2, f"rc {r.returncode}\n--- stdout\n{r.stdout[-2000:]}\n--- stderr\n{r.stderr[-3000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(prefix)]
    assert len(lines) == 1, f"expected one '{prefix}' line:\n{r.stderr[-3000:]}"
    for name in case.names(k):
        assert name in lines[0], f"{name!r} not named in: {lines[0]}"
    if out.exists():
        left = [p for p in PRODUCTS if (out / p).exists()]
        assert not left, f"finished-looking products left in --out: {left}"


# ------------------------------------------------------------------ faults of the machine (issue 37)
def _error_line(r: subprocess.CompletedProcess, command: str) -> str:
    """The one ``tiledsm COMMAND: error:`` line of a refused command (exit
    code 2, no traceback)."""
    prefix = f"tiledsm {command}: error:"
    assert r.returncode == 2, f"rc {r.returncode}\n--- stdout\n{r.stdout[-2000:]}\n--- stderr\n{r.stderr[-3000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(prefix)]
    assert len(lines) == 1, f"expected one '{prefix}' line:\n{r.stderr[-3000:]}"
    return lines[0]


@pytest.fixture
def not_a_scheduler(request):
    """``tcp://127.0.0.1:PORT`` of a plain TCP server of this test that
    accepts and sends ``request.param`` (bytes), or nothing (``None``)
    while holding the connection open."""
    import socket
    import threading

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held = []

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:  # closed at the test's end
                return
            if request.param is not None:
                conn.sendall(request.param)
            held.append(conn)

    threading.Thread(target=serve, daemon=True).start()
    yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    server.close()
    for conn in held:
        conn.close()


def _scheduler_refused(k, tmp_path, capsys, address: str, *extra: str) -> tuple[str, float]:
    """``tiledsm dsm --scheduler ADDRESS --overwrite`` into a folder holding
    an earlier run's products (``python -m tiledsm``) and into a new folder
    (:func:`tiledsm.cli.main` in this process, timed: the interpreter's
    start and imports left out): the error line, the same for both, and
    the seconds the second took; nothing created or withdrawn."""
    import time

    from tiledsm.cli import main

    earlier, new = tmp_path / "earlier", tmp_path / "new"
    earlier.mkdir()
    kept = {name: f"an earlier run's {name}".encode() for name in ("dsm.tif", "metrics.json")}
    for name, data in kept.items():
        (earlier / name).write_bytes(data)
    argv = lambda out: ["dsm", str(k["v0"]), str(k["v1"]), "--out", str(out), "--scheduler", address,  # noqa: E731
                        "--overwrite", "--no-progress", *extra]
    r = subprocess.run([sys.executable, "-m", "tiledsm", *argv(earlier)], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    line = _error_line(r, "dsm")
    assert {p.name: p.read_bytes() for p in earlier.iterdir()} == kept  # nothing withdrawn, nothing added
    capsys.readouterr()
    t0 = time.monotonic()
    code = main(argv(new))
    seconds = time.monotonic() - t0
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == line.replace(str(earlier), str(new)), err
    assert not new.exists()
    return line, seconds


@pytest.mark.parametrize("address, problem", [
    ("tcp://127.0.0.1:9", "nothing accepts a connection there"),
    ("tcp://no-such-host.invalid:8786", "cannot resolve the host"),
], ids=["nothing-listening", "unresolvable-host"])
@pytest.mark.parametrize("dry", [(), ("--dry-run",)], ids=["run", "dry-run"])
def test_unreachable_scheduler_is_refused_by_the_plan(k, tmp_path, capsys, address, problem, dry):
    line, seconds = _scheduler_refused(k, tmp_path, capsys, address, *dry)
    assert f"--scheduler {address}" in line and problem in line, line
    assert seconds < 10, f"answered in {seconds:.1f} s"


@pytest.mark.parametrize("not_a_scheduler, problem", [
    (None, "sent no handshake within"),
    (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n", "its first bytes are b'HTTP/1.1'"),
], ids=["silent", "garbage"], indirect=["not_a_scheduler"])
def test_a_tcp_server_that_is_no_scheduler_is_refused_by_the_plan(k, tmp_path, capsys, not_a_scheduler, problem):
    line, seconds = _scheduler_refused(k, tmp_path, capsys, not_a_scheduler)
    assert f"--scheduler {not_a_scheduler}" in line and "not a dask scheduler" in line and problem in line, line
    assert seconds < 10, f"answered in {seconds:.1f} s"


def test_a_real_scheduler_passes_the_plan_and_its_workers_are_counted(k, tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp",
                      dashboard_address=":0") as cluster:
        r = subprocess.run([sys.executable, "-m", "tiledsm", "dsm", str(k["v0"]), str(k["v1"]), "--out",
                            str(tmp_path / "out"), "--scheduler", cluster.scheduler_address, "--dry-run"],
                           capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"existing cluster at {cluster.scheduler_address}: 2 workers now" in r.stdout, r.stdout
    assert not (tmp_path / "out").exists()


@pytest.fixture
def mounted(tmp_path):
    """``mount(options)``: a fresh tmpfs folder mounted with ``options``
    (e.g. ``ro`` or ``size=64k``: a read-only or a small disk), unmounted
    at the test's end; the test is skipped where this user may not mount."""
    mounts = []

    def mount(options: str) -> Path:
        where = tmp_path / f"mnt{len(mounts)}"
        where.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip()})")
        mounts.append(where)
        return where

    yield mount
    for where in reversed(mounts):
        subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.fixture
def read_only_folder(tmp_path, mounted) -> Path:
    """A folder this user cannot write into: a read-only tmpfs for root
    (whom permissions do not stop), a folder without write permission for
    anyone else."""
    if os.geteuid() == 0:
        yield mounted("ro,size=64k")
        return
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    yield folder
    folder.chmod(0o755)


@pytest.mark.parametrize("where", ["the-folder", "below-it"])
@pytest.mark.parametrize("command", ["dsm", "sr"])
def test_unwritable_output_is_refused_by_the_plan(k, tmp_path, read_only_folder, command, where):
    out = read_only_folder if where == "the-folder" else read_only_folder / "new" / "out"
    argv = (["dsm", str(k["v0"]), str(k["v1"]), "--out", str(out)] if command == "dsm"
            else ["sr", str(k["v0"]), str(out), "--model", "bicubic"])
    r = subprocess.run([sys.executable, "-m", "tiledsm", *argv], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    line = _error_line(r, command)
    reason = "read-only file system" if os.geteuid() == 0 else "permission denied"
    assert f"{read_only_folder}: " in line and reason in line, line
    assert "--out" in line, line  # sr's OUT is its --out
    assert list(read_only_folder.iterdir()) == []


@pytest.mark.parametrize("command", ["dsm", "sr"])
def test_full_disk_is_one_line_naming_the_output(k, tmp_path, mounted, command):
    """Onto a disk too small for the products (a 120 KiB tmpfs): ``sr``'s
    320² float32 GeoTIFF needs 400 KiB, and GDAL's failed write becomes one
    line naming the output and the room on its disk, no temporary left;
    ``dsm``'s store fills the disk (zarr's ``OSError`` without a file name):
    one line naming --out."""
    disk = mounted("size=120k")
    out = disk / "out"
    argv = (["dsm", str(k["v0"]), str(k["v1"]), "--out", str(out), "--scheduler", "synchronous", "--no-progress"]
            if command == "dsm" else ["sr", str(k["v0"]), str(out), "--model", "bicubic"])
    r = subprocess.run([sys.executable, "-m", "tiledsm", *argv], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    line = _error_line(r, command)
    if command == "sr":
        assert f"{out}: cannot write it (" in line and "MiB free on its disk" in line, line  # the OUT given
        assert sorted(p.name for p in out.iterdir()) == ["run.log"]  # no product, no temporary, no metrics
    else:
        assert line.endswith(f"error: {out}: No space left on device (writing into it)"), line
        assert not (out / "metrics.json").exists() and not (out / "dsm.tif").exists()


@pytest.mark.parametrize("command", ["dsm", "sr"])
def test_a_write_that_fails_mid_run_is_one_line(k, tmp_path, monkeypatch, capsys, command):
    """Wherever the machine stops a write (full disk, quota, a folder made
    read-only during the run: an ``OSError`` with its errno), the command
    ends with one line naming the file and the system's reason, exit code
    2, no traceback; simulated in this process on the GeoTIFF writer that
    both commands end with."""
    import errno

    import tiledsm.io.export as export
    from tiledsm.cli import main

    def full(data, path, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(export, "_write_gtiff", full)
    out = tmp_path / "out"
    argv = (["dsm", str(k["v0"]), str(k["v1"]), "--out", str(out), "--scheduler", "synchronous", "--no-progress"]
            if command == "dsm" else ["sr", str(k["v0"]), str(out), "--model", "bicubic"])
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"tiledsm {command}: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    name = "dsm.tif" if command == "dsm" else "sr.tif"
    assert f"/.{name}.tmp-" in lines[0] and lines[0].endswith(": No space left on device"), lines[0]
    left = [p.name for p in out.iterdir() if ".tmp-" in p.name]
    assert not left, left


def test_read_only_installation_runs_for_a_user_without_a_writable_home(k, tmp_path, mounted):
    """A copy of the package that nobody may write into (a read-only tmpfs
    for root, files without write permission for anyone else), run with a
    home that cannot be written either: numba can cache its kernels
    (``cache=True``) neither beside their sources nor in ``~/.cache``, and
    compiled none before tiledsm pointed it at the temporary folder
    (``RuntimeError: cannot cache function '_rational': no locator
    available``). ``--help`` and ``info`` (which compiles the RPC kernel)
    work, and the kernel is cached in the temporary folder."""
    import tiledsm

    source = Path(tiledsm.__file__).parent
    if os.geteuid() == 0:
        installed, home = mounted("size=64m"), mounted("ro,size=64k")
    else:
        installed, home = tmp_path / "site", tmp_path / "home"
        installed.mkdir()
        home.mkdir()
    shutil.copytree(source, installed / "tiledsm", ignore=shutil.ignore_patterns("__pycache__"))
    if os.geteuid() == 0:
        subprocess.run(["mount", "-o", "remount,ro", str(installed)], check=True)
    else:
        for p in [*installed.rglob("*"), installed, home]:
            p.chmod(p.stat().st_mode & ~0o222)
    temp = tmp_path / "temp"
    temp.mkdir()
    env = {key: v for key, v in os.environ.items() if key not in ("XDG_CACHE_HOME", "NUMBA_CACHE_DIR")}
    env.update(HOME=str(home), TMPDIR=str(temp), PYTHONPATH=str(installed))
    for argv in (["--help"], ["info", str(k["v0"])]):
        r = subprocess.run([sys.executable, "-m", "tiledsm", *argv], capture_output=True, text=True, timeout=300,
                           cwd=tmp_path, env=env)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert "gsd_m" in r.stdout, r.stdout
    index = list(temp.glob("tiledsm-numba-cache-*/*/rpc._rational-*.nbi"))
    assert index, list(temp.rglob("*"))
    assert not list(installed.rglob("__pycache__"))
    # the next start loads the kernel: the stale-kernel check keeps its state
    # there too, and removes nothing (tiledsm.kernel_cache)
    assert list(temp.glob("tiledsm-numba-cache-*/tiledsm-kernel-state/*.json"))
    stamp = index[0].stat().st_mtime_ns
    r = subprocess.run([sys.executable, "-m", "tiledsm", "info", str(k["v0"])], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path, env=env)
    assert r.returncode == 0 and index[0].stat().st_mtime_ns == stamp, r.stderr[-3000:]


def test_a_run_killed_during_the_export_leaves_no_temporary_after_its_rerun(k, tmp_path):
    """``tiledsm dsm`` killed (SIGKILL) while it exports ``dsm.tif``: its
    uncompressed full-grid source ``.dsm.tif.tmp-*.tif.src.tif`` is left
    (a killed process cleans nothing). The rerun, on taking the folder's
    lock, removes it and GDAL's ``.ovr.tmp`` beside it, and ends with a
    DSM equal to a clean run's. The export waits between its source and the
    COG while ``TILEDSM_TEST_EXPORT_PAUSE_S`` is set: the kill lands there."""
    import signal
    import time

    from tiledsm.io.atomic import TEMPORARY
    from tiledsm.io.export import EXPORT_PAUSE_ENV

    def cmd(out):
        return [sys.executable, "-m", "tiledsm", "dsm", str(k["v0"]), str(k["v1"]), "--out", str(out),
                "--scheduler", "synchronous", "--no-progress"]

    def temporaries(out):
        return sorted(p.name for p in out.rglob("*") if TEMPORARY.match(p.name))

    clean, out = tmp_path / "clean", tmp_path / "out"
    r = subprocess.run(cmd(clean), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    killed = subprocess.Popen(cmd(out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              env={**os.environ, EXPORT_PAUSE_ENV: "120"})
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob(".dsm.tif.tmp-*.src.tif")):
            assert killed.poll() is None and time.monotonic() < deadline, "the export never started"
            time.sleep(0.2)
    finally:
        killed.send_signal(signal.SIGKILL)
        killed.wait(timeout=60)
    left = temporaries(out)
    assert len(left) == 1 and left[0].endswith(".tif.src.tif"), left
    source = out / left[0]
    ovr = source.with_name(source.name.removesuffix(".src.tif") + ".ovr.tmp")  # GDAL's, when killed in the COG
    ovr.write_bytes(b"overviews")
    assert not (out / "dsm.tif").exists()

    r = subprocess.run(cmd(out), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert temporaries(out) == []
    assert "removed 2 temporaries an interrupted run left" in (out / "run.log").read_text() + r.stderr
    with rasterio.open(clean / "dsm.tif") as a, rasterio.open(out / "dsm.tif") as b:
        np.testing.assert_array_equal(a.read(), b.read())
        assert a.transform == b.transform and a.crs == b.crs


def test_cells_finer_than_a_fifth_of_the_gsd_warn_in_the_plan_and_the_run_log(k, tmp_path):
    """A 0.05 m DSM from 0.5 m images (on a 6 m square: 120² cells) runs,
    but warns, naming --resolution and both sizes, on stderr, in
    ``run.log`` and in ``metrics.json``; 0.1 m (a fifth) does not."""
    with rasterio.open(k["truth"]) as src:
        x, y = (src.bounds.left + src.bounds.right) / 2, (src.bounds.bottom + src.bounds.top) / 2
        crs = src.crs.to_string()
    bounds = [str(v) for v in (x - 3, y - 3, x + 3, y + 3)]
    warned = "cells of 0.05 m are finer than a fifth of the images' GSD (0.5 m)"
    for resolution, warns in (("0.05", True), ("0.1", False)):
        out = tmp_path / resolution
        r = subprocess.run([sys.executable, "-m", "tiledsm", "dsm", str(k["v0"]), str(k["v1"]), "--out", str(out),
                            "--bounds", *bounds, "--crs", crs, "--resolution", resolution, "--scheduler", "synchronous",
                            "--no-progress"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert r.returncode == 0, r.stderr[-3000:]
        lines = [ln for ln in r.stderr.splitlines() if "finer than a fifth" in ln]
        if not warns:
            assert not lines and "finer than a fifth" not in (out / "run.log").read_text(), r.stderr
            continue
        assert len(lines) == 1 and lines[0].startswith(f"tiledsm dsm: warning: --resolution 0.05: {warned}"), r.stderr
        assert "2,500 times" not in lines[0] and "100 times the cells" in lines[0], lines[0]
        assert warned in (out / "run.log").read_text()
        assert any(warned in w for w in json.loads((out / "metrics.json").read_text())["warnings"])


def test_allow_large_dry_run_of_a_huge_grid_prints_its_plan_in_seconds(k, tmp_path, capsys):
    """``--resolution 0.0005 --allow-large --dry-run`` from 0.5 m images:
    a 40.6 Gcell grid in 402 x 386 = 155 172 chunks. Its plan built the
    graph's dependencies by scanning every chunk of a row for each chunk
    (102 s on the 2-core development machine); now a binary search (10 s
    there). The plan is printed, with the GSD warning, and nothing is
    written. Timed in this process (:func:`tiledsm.cli.main`). The graph
    counts the engine's token aliases (each reader takes its writers' tokens
    through ``Array.blocks``): 2.64 M tasks, 4.25x those of the hand-built
    graph it replaced."""
    import time

    from tiledsm.cli import main

    out = tmp_path / "out"
    t0 = time.monotonic()
    code = main(["dsm", str(k["v0"]), str(k["v1"]), "--out", str(out), "--resolution", "0.0005", "--allow-large",
                 "--dry-run"])
    seconds = time.monotonic() - t0
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "402 x 386 = 155172" in captured.out and "2,637,926 in the dask graph" in captured.out, captured.out
    assert "cells of 0.0005 m are finer than a fifth of the images' GSD (0.5 m)" in captured.err, captured.err
    assert not out.exists()
    assert seconds < 45, f"the plan took {seconds:.0f} s"
