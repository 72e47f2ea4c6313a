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
    Case("dsm-device-unknown", dsm("--device", "gpu7"), lambda f: ["--device", "gpu7", "not a torch device"]),
    # a CUDA device that this machine lacks (cuda:64: no machine has that many)
    Case("dsm-device-absent", dsm("--device", "cuda:64"), lambda f: ["--device", "cuda:64"]),
    Case("dsm-memory-per-worker-not-a-size", dsm("--memory-per-worker", "lots"), lambda f: ["--memory-per-worker", "lots"]),
    # --- sr
    Case("sr-missing-input", lambda f, out: ["sr", str(f["root"] / "nope.tif"), str(out / "sr.tif")], lambda f: ["nope.tif"]),
    Case("sr-scale-without-weights", lambda f, out: ["sr", str(f["v0"]), str(out / "sr.tif"), "--model", "srcnn", "--scale", "3"],
         lambda f: ["--scale"]),
    Case("sr-truncated-input", lambda f, out: ["sr", str(f["truncated"]), str(out / "sr.tif")], lambda f: ["truncated.tif"]),
    Case("sr-output-exists", lambda f, out: ["sr", str(f["v0"]), str(f["earlier_sr"]), "--model", "bicubic"],
         lambda f: ["earlier_sr.tif", "--overwrite"]),
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
    if case.id.startswith("sr-"):
        out.mkdir()  # sr writes a file: its folder exists, the input is what is wrong
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
