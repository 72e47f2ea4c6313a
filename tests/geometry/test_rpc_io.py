"""RPC files of many sensors/formats against GDAL (rasterio's RPCTransformer),
format cross-checks, errors, and camera discovery (find_camera)."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import RPCTransformer

from tests.conftest import SHARED_DATA, require_shared
from tiledsm.errors import InputFileError, RPCError, UnsupportedFormatError
from tiledsm.geometry import RPC
from tiledsm.io.cameras import find_camera, read_rpc

RPCM = ["20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT", "JAX_068_001_RGB.json",
        "rpc_IKONOS.txt", "rpc_PLANET_L1A.txt", "rpc_PLANET_L1B.txt", "rpc_PLEIADES.xml", "rpc_SPOT6.xml",
        "rpc_WV1.xml", "rpc_WV2.xml", "rpc_WV3.xml"]
SHARELOC = ["PHR1B_P_201709281038045_SEN_PRG_FC_178608-001.geom",
            "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.geom",
            "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif", "PHRDIMAP_P1BP--2018122638935449CP.XML",
            "RPC_PHR1A_P_202503191043438_SEN_7342362101-1.XML",
            "RPC_PHR1B_P_201709281038045_SEN_PRG_FC_178608-001.XML",
            "RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML", "wv3_20.NTF", "wv3_30.NTF"]
FILES = ([("rpc_models", "rpcm", f) for f in RPCM] + [("rpc_models", "shareloc", f) for f in SHARELOC]
         + [("s2p_pair", "input_pair", f) for f in ("img_01.tif", "img_02.tif")]
         + [("shareloc_phr_ventoux", f) for f in ("left_image.geom", "right_image.geom",
                                                   "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")])
EXPECTED_FORMAT = {".txt": "txt", ".TXT": "txt", ".json": "json", ".geom": "ossim_geom", ".tif": "gdal",
                   ".NTF": "gdal"}


def _image_points(rpc: RPC, path: Path):
    """5x5 grid of pixel positions across the image (GDAL convention)."""
    if path.suffix in (".tif", ".NTF"):
        with rasterio.open(path) as ds:
            r0, r1, c0, c1 = 0.0, float(ds.height), 0.0, float(ds.width)
    else:
        r0, r1, c0, c1 = rpc.image_window()
    rows, cols = np.meshgrid(np.linspace(r0, r1, 5), np.linspace(c0, c1, 5), indexing="ij")
    return rows.ravel(), cols.ravel()


@pytest.mark.parametrize("parts", FILES, ids=[p[-1][:40] for p in FILES])
def test_against_gdal(parts):
    path = require_shared(*parts)
    rpc = read_rpc(path)
    fmt = rpc.source.rsplit("(", 1)[1].rstrip(")")
    if path.suffix in EXPECTED_FORMAT:
        assert fmt == EXPECTED_FORMAT[path.suffix]
    if fmt == "gdal":  # GDAL parsed it itself: ours must be the same model
        with rasterio.open(path) as ds:
            assert RPC.from_gdal(ds.rpcs.to_dict()) == rpc
    rows, cols = _image_points(rpc, path)
    gdal_tol = 1e-6  # px: GDAL's iteration threshold (its default is 0.1 px)
    opts = {"RPC_PIXEL_ERROR_THRESHOLD": gdal_tol, "RPC_MAX_ITERATIONS": 100}
    with RPCTransformer(rpc.to_gdal(), **opts) as tr:
        for frac in (-0.5, 0.0, 0.5):  # three heights across the validity range
            h = np.full(rows.shape, rpc.height_off + frac * rpc.height_scale)
            lon, lat = rpc.localize(rows, cols, h)
            # projection: ours vs GDAL at our ground points
            gr, gc = tr.rowcol(lon, lat, zs=h, op=lambda x: x)
            pr, pc = rpc.project(lon, lat, h)
            assert np.max(np.hypot(pr - np.asarray(gr), pc - np.asarray(gc))) < 1e-3
            # localisation round-trips through project
            assert np.max(np.hypot(pr - rows, pc - cols)) < 1e-4
            # localisation agrees with GDAL's within GDAL's tolerance: the two
            # ground points are within gdal_tol px of each other in the image
            gx, gy = tr.xy(rows, cols, zs=h, offset="ul")
            gx, gy = np.asarray(gx), np.asarray(gy)
            assert np.all(np.isfinite(gx)), "GDAL failed to localise"
            qr, qc = rpc.project(gx, gy, h)
            assert np.max(np.hypot(qr - pr, qc - pc)) < 2 * gdal_tol


def _gdal_sidecar(tmp_path: Path, src: Path, image_name: str, sidecar_name: str):
    """Let GDAL itself parse ``src`` as the sidecar of a dummy image."""
    img = tmp_path / image_name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(img, "w", driver="GTiff", width=4, height=4, count=1, dtype="uint8"):
            pass
    shutil.copy(src, tmp_path / sidecar_name)
    with rasterio.open(img) as ds:
        assert ds.rpcs is not None, f"GDAL did not read {sidecar_name}"
        return img, RPC.from_gdal(ds.rpcs.to_dict())


@pytest.mark.parametrize("name,sidecar", [
    ("rpc_IKONOS.txt", "a_RPC.TXT"), ("rpc_PLANET_L1A.txt", "a_RPC.TXT"), ("rpc_PLANET_L1B.txt", "a_RPC.TXT"),
    ("20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT", "a_RPC.TXT"),
    ("rpc_WV1.xml", "a.XML"), ("rpc_WV2.xml", "a.XML"), ("rpc_WV3.xml", "a.XML"),
])
def test_gdal_own_parser_agrees(tmp_path, name, sidecar):
    """GDAL reads _RPC.TXT and DigitalGlobe XML sidecars itself: same model."""
    src = require_shared("rpc_models", "rpcm", name)
    img, theirs = _gdal_sidecar(tmp_path, src, "a.tif", sidecar)
    assert read_rpc(src) == theirs
    cam, where = find_camera(img)
    assert cam == theirs
    assert "sidecar" in where and sidecar in where


def _project_all(rpcs, n=200, seed=0):
    ref = rpcs[0]
    rng = np.random.default_rng(seed)
    lon = ref.lon_off + ref.lon_scale * rng.uniform(-0.8, 0.8, n)
    lat = ref.lat_off + ref.lat_scale * rng.uniform(-0.8, 0.8, n)
    h = ref.height_off + ref.height_scale * rng.uniform(-0.8, 0.8, n)
    return [np.stack(r.project(lon, lat, h)) for r in rpcs]


def test_phr_tif_geom_dimap_agree():
    base = "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001"
    rpcs = [read_rpc(require_shared("rpc_models", "shareloc", f))
            for f in (base + ".tif", base + ".geom", "RPC_" + base + ".XML")]
    p = _project_all(rpcs)
    assert np.max(np.abs(p[1] - p[0])) < 1e-3
    assert np.max(np.abs(p[2] - p[0])) < 1e-3  # DIMAP's 1-based offsets shifted by -1


def test_ventoux_geom_and_dimap_agree():
    p = _project_all([read_rpc(require_shared("shareloc_phr_ventoux", f))
                      for f in ("left_image.geom", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")])
    assert np.max(np.abs(p[1] - p[0])) < 1e-3


def test_dimap_v1_inverse_matches_its_direct_model():
    """DIMAP v1 carries both models; our inverse (image->ground by Newton)
    must reproduce the file's direct RFM (F_LON/F_LAT) to its stated ~1e-3 px."""
    import xml.etree.ElementTree as ET

    from tiledsm.geometry.rpc import rpc_terms

    path = require_shared("rpc_models", "shareloc", "PHRDIMAP_P1BP--2018122638935449CP.XML")
    rpc = read_rpc(path)
    rfm = ET.parse(path).getroot().find(".//Rational_Sensor_Model/Global_RFM")
    f = {k: np.array(rfm.find(f"Direct_Model/{k}").text.split(), float) for k in ("F_LON", "F_LAT")}
    rng = np.random.default_rng(0)
    row = rng.uniform(1, 38248, 200)  # 1-based DIMAP coordinates of pixel centres
    col = rng.uniform(1, 40000, 200)
    h = rng.uniform(500, 650, 200)
    t = rpc_terms((col - 20000.5) / 19999.5, (row - 19124.5) / 19123.5, (h - 575) / 85)
    lon = (f["F_LON"][:20] @ t) / (f["F_LON"][20:] @ t) * 0.1118051886786475 + 2.230206949755298
    lat = (f["F_LAT"][:20] @ t) / (f["F_LAT"][20:] @ t) * 0.09554999162856959 + 31.01867988652799
    # DIMAP 1-based centre (r, c) is GDAL (r - 0.5, c - 0.5)
    pr, pc = rpc.project(lon, lat, h)
    assert np.max(np.hypot(pr - (row - 0.5), pc - (col - 0.5))) < 5e-3


def test_planet_l1a_l1b_same_model_other_scaling():
    """rpcm's fact, what it means here: same normalised projection, different
    offsets/scales, i.e. L1B = L1A resampled by LINE_SCALE ratio."""
    a = read_rpc(require_shared("rpc_models", "rpcm", "rpc_PLANET_L1A.txt"))
    b = read_rpc(require_shared("rpc_models", "rpcm", "rpc_PLANET_L1B.txt"))
    assert a.line_off != b.line_off and a.samp_scale != b.samp_scale
    pa, pb = _project_all([a, b])
    na = (pa[0] - 0.5 - a.line_off) / a.line_scale, (pa[1] - 0.5 - a.samp_off) / a.samp_scale
    nb = (pb[0] - 0.5 - b.line_off) / b.line_scale, (pb[1] - 0.5 - b.samp_off) / b.samp_scale
    np.testing.assert_allclose(na, nb, atol=1e-12)


@pytest.mark.parametrize("h", [70.0, 90.0])
def test_skysat_corner_localisation_converges(h):
    """rpcm's SkySat iteration fails for pixel (0, 0) at 70 m; our Newton
    converges at both heights and GDAL (run to 1e-6 px) finds the same point."""
    rpc = read_rpc(require_shared("rpc_models", "rpcm",
                                  "20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT"))
    lon, lat = rpc.localize(0.0, 0.0, h)
    r, c = rpc.project(lon, lat, h)
    assert abs(r) < 1e-6 and abs(c) < 1e-6
    with RPCTransformer(rpc.to_gdal(), RPC_PIXEL_ERROR_THRESHOLD=1e-6, RPC_MAX_ITERATIONS=100) as tr:
        gx, gy = tr.xy(0.0, 0.0, zs=h, offset="ul")
    gr, gc = rpc.project(gx, gy, h)
    assert abs(gr - r) < 2e-6 and abs(gc - c) < 2e-6


# ---------------------------------------------------------------------- errors
def test_missing_file():
    with pytest.raises(InputFileError, match="no_such.geom"):
        read_rpc("/nonexistent/no_such.geom")


def test_unsupported_format():
    path = require_shared("rpc_models", "rpcm", "rpc_unsupported.xml")
    with pytest.raises(UnsupportedFormatError, match="rpc_unsupported.xml"):
        read_rpc(path)


def test_text_without_rpc_keys(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("hello: world\n")
    with pytest.raises(UnsupportedFormatError, match="notes.txt"):
        read_rpc(p)


def _ikonos_lines():
    return require_shared("rpc_models", "rpcm", "rpc_IKONOS.txt").read_text().splitlines()


def test_wrong_coefficient_count(tmp_path):
    p = tmp_path / "short_RPC.TXT"
    p.write_text("\n".join(l for l in _ikonos_lines() if not l.startswith("SAMP_DEN_COEFF_20")))
    with pytest.raises(RPCError, match=r"short_RPC.TXT.*samp_den has 19 coefficients"):
        read_rpc(p)


def test_non_finite_coefficient(tmp_path):
    p = tmp_path / "nan_RPC.TXT"
    p.write_text("\n".join("LINE_NUM_COEFF_3: nan" if l.startswith("LINE_NUM_COEFF_3:") else l
                           for l in _ikonos_lines()))
    with pytest.raises(RPCError, match=r"nan_RPC.TXT.*line_num has non-finite"):
        read_rpc(p)


def test_missing_key_geom(tmp_path):
    src = require_shared("shareloc_phr_ventoux", "left_image.geom").read_text()
    p = tmp_path / "x.geom"
    p.write_text("\n".join(l for l in src.splitlines() if not l.startswith("lat_scale")))
    with pytest.raises(RPCError, match=r"x.geom.*LAT_SCALE"):
        read_rpc(p)


# ---------------------------------------------------------------- find_camera
def test_find_camera_tiff_tags():
    img = require_shared("s2p_pair", "input_pair", "img_01.tif")
    cam, where = find_camera(img)
    assert "RPC metadata" in where and "img_01.tif" in where
    with rasterio.open(img) as ds:
        assert cam == RPC.from_gdal(ds.rpcs.to_dict())


def test_find_camera_ventoux_crop():
    """left_image.tif is a crop at (row, col) = (5000, 5000) of the image that
    left_image.geom describes: crop coordinates = full coordinates - offset."""
    img = require_shared("shareloc_phr_ventoux", "left_image.tif")
    cam, where = find_camera(img)
    assert "left_image.geom" in where and "cropped at row 5000, col 5000" in where
    full = read_rpc(img.with_suffix(".geom"))
    lon, lat = cam.localize([0.5, 250.0, 499.5], [0.5, 250.0, 499.5], 500.0)
    fr, fc = full.project(lon, lat, 500.0)
    np.testing.assert_allclose(fr - 5000, [0.5, 250.0, 499.5], atol=1e-6)
    np.testing.assert_allclose(fc - 5000, [0.5, 250.0, 499.5], atol=1e-6)
    # the biased RPC given explicitly is used instead (line_off + 60)
    biased, where = find_camera(img, rpc=img.parent / "right_image_bias.geom")
    assert "explicit file" in where and "right_image_bias.geom" in where


def test_find_camera_none(tmp_path):
    img = tmp_path / "plain.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(img, "w", driver="GTiff", width=4, height=4, count=1, dtype="uint8"):
            pass
    (tmp_path / "plain.xml").write_text("<foo/>")
    with pytest.raises(RPCError, match=r"plain.tif: no camera found.*plain.xml"):
        find_camera(img)
    with pytest.raises(InputFileError, match="missing.tif"):
        find_camera(tmp_path / "missing.tif")


def test_ventoux_left_right_offset_with_srtm_and_egm96():
    """Data README: with SRTM + EGM96 the predicted left->right offset is
    (drow -316, dcol +85) (NCC says -321, +80); with SRTM heights used as
    ellipsoidal heights it is off by tens of pixels."""
    from tiledsm.io.geoid import geoid_to_ellipsoid

    d = require_shared("shareloc_phr_ventoux")
    left, _ = find_camera(d / "left_image.tif")
    right, _ = find_camera(d / "right_image.tif")
    with rasterio.open(d / "srtm" / "N44E005.hgt") as ds:
        dem, inv = ds.read(1).astype(float), ~ds.transform

    def srtm(lon, lat):
        c, r = inv @ (lon, lat)
        return dem[int(np.floor(r)), int(np.floor(c))]

    def offset(ellipsoidal: bool):
        row, col, h = 250.0, 250.0, 500.0
        for _ in range(6):  # fixed point: localise at h, read the DEM there
            lon, lat = left.localize(row, col, h)
            h = srtm(lon, lat)
            if ellipsoidal:
                h = float(geoid_to_ellipsoid(lon, lat, h, d / "geoid" / "egm96_15.gtx"))
        rr, rc = right.project(lon, lat, h)
        return rr - row, rc - col

    dr, dc = offset(True)
    # measured at the left crop centre: (-320.9, +85.9); the README's point is
    # not stated, its prediction and NCC differ by ~5 px, so allow 6 px to both
    assert abs(dr - (-316)) < 6 and abs(dc - 85) < 6
    assert abs(dr - (-321)) < 6 and abs(dc - 80) < 6
    dr0, dc0 = offset(False)
    assert np.hypot(dr0 - dr, dc0 - dc) > 20


# ----------------------------------------------------------------- writers
def _tiny_raster(path: Path, shape=(24, 32)) -> Path:
    data = np.arange(shape[0] * shape[1], dtype=np.uint16).reshape(shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", driver="GTiff", width=shape[1], height=shape[0], count=1,
                           dtype="uint16") as ds:
            ds.write(data, 1)
    return path


def _wv3_rpc():
    return read_rpc(require_shared("rpc_models", "rpcm", "rpc_WV3.xml"))


def _gdal_agrees(path: Path, rpc: RPC, n: int = 50) -> None:
    """rasterio reads back exactly ``rpc`` and its RPC transformer projects
    like :meth:`RPC.project` (1e-3 px: GDAL's own iteration tolerance)."""
    from tiledsm.io import cameras as rpc_io

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            got = RPC.from_gdal(ds.rpcs.to_dict())
            with RPCTransformer(ds.rpcs) as tr:
                rng = np.random.default_rng(0)
                h = rng.uniform(rpc.height_off - 50, rpc.height_off + 50, n)
                lon, lat = rpc.localize(rng.uniform(0, 2000, n), rng.uniform(0, 2000, n), h)
                gr, gc = tr.rowcol(lon, lat, zs=h, op=lambda x: x)
    assert got == rpc
    r, c = rpc.project(lon, lat, h)
    np.testing.assert_allclose(np.asarray(gr), r, atol=1e-3)
    np.testing.assert_allclose(np.asarray(gc), c, atol=1e-3)
    assert rpc_io.format_rpc_txt(got) == rpc_io.format_rpc_txt(rpc)


def test_rpc_txt_written_is_read_by_gdal_and_by_us(tmp_path):
    from tiledsm.io.cameras import rpc_txt_path, write_rpc_txt

    rpc = _wv3_rpc().cropped(10.5, -3.25)
    img = _tiny_raster(tmp_path / "scene.tif")
    side = write_rpc_txt(rpc, rpc_txt_path(img))
    assert side.name == "scene_RPC.TXT"
    _gdal_agrees(img, rpc)
    assert read_rpc(side) == rpc
    assert "txt" in read_rpc(side).source
    cam, origin = find_camera(img)
    assert cam == rpc and "sidecar" in origin


def test_rpc_tags_written_on_an_open_geotiff(tmp_path):
    from tiledsm.io.cameras import write_rpc_tags

    rpc = _wv3_rpc()
    img = _tiny_raster(tmp_path / "scene.tif")
    write_rpc_tags(img, rpc)
    assert not (tmp_path / "scene.RPB").exists()  # inside the file, no sidecar
    _gdal_agrees(img, rpc)
    write_rpc_tags(img, rpc.cropped(5, 5))  # replaced, not appended
    _gdal_agrees(img, rpc.cropped(5, 5))


def test_rpc_tags_refuse_non_geotiff(tmp_path):
    from tiledsm.io.cameras import write_rpc_tags

    p = tmp_path / "x.png"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(p, "w", driver="PNG", width=8, height=8, count=1, dtype="uint8") as ds:
            ds.write(np.zeros((1, 8, 8), np.uint8))
    with pytest.raises(InputFileError, match="x.png"):
        write_rpc_tags(p, _wv3_rpc())
