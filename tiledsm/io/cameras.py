"""Reading RPC camera models from files, and finding the camera of an image.

Formats (detected from the content, not the extension):

========================  ==================================================
``gdal``                  raster with RPC metadata read by GDAL: GeoTIFF
                          tags, NITF RPC00B TRE, ``.RPB`` / ``_RPC.TXT``
                          sidecars of a raster
``rpb``                   a bare ``.RPB`` file (DigitalGlobe keyword list)
``txt``                   ``KEY: value [unit]`` lines (IKONOS, Planet,
                          SkySat ``_RPC.TXT``, rpcm's own format)
``dg_xml``                DigitalGlobe ``<isd>`` XML (``RPB/IMAGE``)
``dimap_v2``              DIMAP v2 ``RPC_*.XML`` (Pleiades, SPOT 6/7)
``dimap_v1``              DIMAP v1 (``PHR_Dimap_Document``, ``F_ROW``/``F_COL``)
``ossim_geom``            OSSIM keyword list (``.geom``, RPC00A or RPC00B)
``json``                  ``{"rpc": {"row_offset": ...}}`` (rpcm/DFC2019)
========================  ==================================================

Every reader returns an :class:`~tiledsm.geometry.rpc.RPC` whose
``line_off``/``samp_off`` follow the RPC standard (first pixel centre at 0);
DIMAP files are 1-based and are shifted by -1. ``RPC.source`` records
``"<path> (<format>)"``.
"""

from __future__ import annotations

import json
import re
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable

import numpy as np

from tiledsm.errors import InputFileError, RPCError, UnsupportedFormatError
from tiledsm.geometry.rpc import RPC

__all__ = [
    "read_rpc", "find_camera", "detect_format", "READERS", "SIDECAR_SUFFIXES",
    "format_rpc_txt", "write_rpc_txt", "write_rpc_tags", "rpc_txt_path",
]

Reader = Callable[[Path, str], RPC]

#: format name -> reader(path, text) (text is None for binary files)
READERS: dict[str, Reader] = {}

#: sidecar names tried by :func:`find_camera`, in order (appended to the image stem)
SIDECAR_SUFFIXES = (".geom", ".RPB", ".rpb", "_RPC.TXT", "_rpc.txt", ".XML", ".xml")


def _register(name: str):
    def deco(fn: Reader) -> Reader:
        if name in READERS:
            raise ValueError(f"RPC reader {name!r} registered twice")
        READERS[name] = fn
        return fn

    return deco


_GDAL_KEYS = (
    "LINE_OFF", "SAMP_OFF", "LAT_OFF", "LONG_OFF", "HEIGHT_OFF",
    "LINE_SCALE", "SAMP_SCALE", "LAT_SCALE", "LONG_SCALE", "HEIGHT_SCALE",
)
_COEFF = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")


def _num(value: str, path: Path, key: str) -> float:
    try:
        return float(value.split()[0])
    except (ValueError, IndexError) as exc:
        raise RPCError(f"{path}: {key} is not a number ({value!r})") from exc


def _nums(values: str, path: Path, key: str) -> list[float]:
    try:
        return [float(t) for t in values.replace(",", " ").split()]
    except ValueError as exc:
        raise RPCError(f"{path}: {key} has non-numeric values") from exc


def _build(md: dict, path: Path, fmt: str) -> RPC:
    """RPC from a GDAL-style dict, errors naming the file."""
    return RPC.from_gdal(md, source=f"{path} ({fmt})")


# ------------------------------------------------------------------ detection
def _read_text(path: Path) -> str | None:
    """The file as text, or None when it looks binary."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if b"\0" in head:
        return None
    try:
        return path.read_text(encoding="utf-8-sig", errors="strict")
    except UnicodeDecodeError:
        try:
            return path.read_text(encoding="latin-1")
        except OSError:  # pragma: no cover
            return None


def detect_format(path: str | Path, text: str | None = None) -> str:
    """Name of the RPC format of ``path`` (a key of :data:`READERS`).

    Raises
    ------
    UnsupportedFormatError
        When the content matches no known format.
    """
    path = Path(path)
    if text is None:
        text = _read_text(path)
    if text is None:
        return "gdal"
    s = text.lstrip()
    if s.startswith("{"):
        return "json"
    if s.startswith("<"):
        try:
            root = ET.fromstring(text.encode("utf-8"))
        except ET.ParseError as exc:
            raise UnsupportedFormatError(f"{path}: malformed XML ({exc})") from exc
        tag = root.tag.split("}")[-1]
        if tag == "isd" and root.find(".//RPB") is not None:
            return "dg_xml"
        if tag.endswith("Dimap_Document"):
            if root.find(".//Rational_Function_Model//Inverse_Model") is not None:
                return "dimap_v2"
            if root.find(".//Rational_Sensor_Model//Inverse_Model/F_ROW") is not None:
                return "dimap_v1"
        raise UnsupportedFormatError(
            f"{path}: XML root <{tag}> is not an RPC format tiledsm reads "
            "(DigitalGlobe <isd> with RPB, DIMAP v1/v2 with an RFM Inverse_Model)"
        )
    if re.search(r"^\s*line_num_coeff_\d+\s*:", text, re.M | re.I) and re.search(
        r"^\s*polynomial_format\s*:", text, re.M
    ):
        return "ossim_geom"
    if re.search(r"^\s*lineOffset\s*=", text, re.M) and "BEGIN_GROUP" in text:
        return "rpb"
    if re.search(r"^\s*LINE_OFF\s*:", text, re.M | re.I) and re.search(r"LINE_NUM_COEFF_1\s*:", text, re.I):
        return "txt"
    # last chance: a raster format GDAL knows whose header is text (e.g. a VRT)
    # is not accepted as a camera: only the formats above are.
    raise UnsupportedFormatError(f"{path}: not a recognised RPC format (text file with no RPC keys)")


# -------------------------------------------------------------------- readers
@_register("gdal")
def _read_gdal(path: Path, text: str | None) -> RPC:
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                rpcs = ds.rpcs
    except RasterioIOError as exc:
        raise UnsupportedFormatError(f"{path}: neither a raster GDAL can open nor an RPC text file") from exc
    if rpcs is None:
        raise RPCError(f"{path}: raster has no RPC metadata")
    return _build({k.upper(): v for k, v in rpcs.to_dict().items()}, path, "gdal")


@_register("txt")
def _read_txt(path: Path, text: str) -> RPC:
    md: dict[str, object] = {}
    coeffs: dict[str, dict[int, float]] = {k: {} for k in _COEFF}
    for line in text.splitlines():
        if ":" not in line:
            continue
        key, _, value = line.partition(":")
        key = key.strip().upper()
        if key in _GDAL_KEYS:
            md[key] = _num(value, path, key)
            continue
        m = re.fullmatch(r"(LINE_NUM|LINE_DEN|SAMP_NUM|SAMP_DEN)_COEFF_(\d+)", key)
        if m:
            coeffs[m.group(1) + "_COEFF"][int(m.group(2))] = _num(value, path, key)
    for k, d in coeffs.items():
        if sorted(d) != list(range(1, len(d) + 1)):
            raise RPCError(f"{path}: {k}_i indices are not 1..n ({sorted(d)[:3]}...)")
        md[k] = [d[i] for i in sorted(d)]
    return _build(md, path, "txt")


@_register("rpb")
def _read_rpb(path: Path, text: str) -> RPC:
    names = {
        "lineOffset": "LINE_OFF", "sampOffset": "SAMP_OFF", "latOffset": "LAT_OFF",
        "longOffset": "LONG_OFF", "heightOffset": "HEIGHT_OFF", "lineScale": "LINE_SCALE",
        "sampScale": "SAMP_SCALE", "latScale": "LAT_SCALE", "longScale": "LONG_SCALE",
        "heightScale": "HEIGHT_SCALE", "lineNumCoef": "LINE_NUM_COEFF", "lineDenCoef": "LINE_DEN_COEFF",
        "sampNumCoef": "SAMP_NUM_COEFF", "sampDenCoef": "SAMP_DEN_COEFF",
    }
    md: dict[str, object] = {}
    for key, value in re.findall(r"(\w+)\s*=\s*([^;]*);", text, re.S):
        if key in names:
            v = value.strip().strip("()")
            md[names[key]] = _nums(v, path, key) if "COEFF" in names[key] else _num(v, path, key)
    return _build(md, path, "rpb")


@_register("dg_xml")
def _read_dg_xml(path: Path, text: str) -> RPC:
    img = ET.fromstring(text.encode()).find(".//RPB/IMAGE")
    if img is None:
        raise RPCError(f"{path}: no RPB/IMAGE element")
    tags = {
        "LINEOFFSET": "LINE_OFF", "SAMPOFFSET": "SAMP_OFF", "LATOFFSET": "LAT_OFF",
        "LONGOFFSET": "LONG_OFF", "HEIGHTOFFSET": "HEIGHT_OFF", "LINESCALE": "LINE_SCALE",
        "SAMPSCALE": "SAMP_SCALE", "LATSCALE": "LAT_SCALE", "LONGSCALE": "LONG_SCALE",
        "HEIGHTSCALE": "HEIGHT_SCALE",
    }
    md: dict[str, object] = {}
    for tag, key in tags.items():
        el = img.find(tag)
        if el is not None and el.text:
            md[key] = _num(el.text, path, tag)
    for key in _COEFF:
        tag = key.replace("_COEFF", "COEF").replace("_", "")  # LINENUMCOEF
        el = img.find(f"{tag}List/{tag}")
        if el is not None and el.text:
            md[key] = _nums(el.text, path, tag)
    return _build(md, path, "dg_xml")


def _dimap_shift(md: dict, path: Path, fmt: str) -> RPC:
    """DIMAP image coordinates are 1-based: shift the offsets by -1."""
    for key in ("LINE_OFF", "SAMP_OFF"):
        if key in md:
            md[key] = float(md[key]) - 1.0
    return _build(md, path, fmt)


@_register("dimap_v2")
def _read_dimap_v2(path: Path, text: str) -> RPC:
    root = ET.fromstring(text.encode())
    inv = root.find(".//Rational_Function_Model//Inverse_Model")
    val = root.find(".//Rational_Function_Model//RFM_Validity")
    md: dict[str, object] = {}
    if val is not None:
        for key in _GDAL_KEYS:
            el = val.find(key)
            if el is not None and el.text:
                md[key] = _num(el.text, path, key)
    for key in _COEFF:
        found = {}
        for el in inv if inv is not None else []:
            m = re.fullmatch(key + r"_(\d+)", el.tag)
            if m:
                found[int(m.group(1))] = _num(el.text or "", path, el.tag)
        if found:
            if sorted(found) != list(range(1, len(found) + 1)):
                raise RPCError(f"{path}: {key}_i indices are not 1..n")
            md[key] = [found[i] for i in sorted(found)]
    return _dimap_shift(md, path, "dimap_v2")


@_register("dimap_v1")
def _read_dimap_v1(path: Path, text: str) -> RPC:
    root = ET.fromstring(text.encode())
    rfm = root.find(".//Rational_Sensor_Model/Global_RFM")
    md: dict[str, object] = {}
    for tag, (num, den) in {"F_ROW": ("LINE_NUM_COEFF", "LINE_DEN_COEFF"),
                            "F_COL": ("SAMP_NUM_COEFF", "SAMP_DEN_COEFF")}.items():
        el = rfm.find(f"Inverse_Model/{tag}")
        vals = _nums(el.text or "", path, tag) if el is not None else []
        if len(vals) != 40:
            raise RPCError(f"{path}: {tag} has {len(vals)} coefficients, expected 40 (20 num + 20 den)")
        md[num], md[den] = vals[:20], vals[20:]
    # RFM_Validity/<Axis>/A = scale, B = offset
    for axis, (scale, off) in {"Lon": ("LONG_SCALE", "LONG_OFF"), "Lat": ("LAT_SCALE", "LAT_OFF"),
                               "Alt": ("HEIGHT_SCALE", "HEIGHT_OFF"), "Col": ("SAMP_SCALE", "SAMP_OFF"),
                               "Row": ("LINE_SCALE", "LINE_OFF")}.items():
        a, b = rfm.find(f"RFM_Validity/{axis}/A"), rfm.find(f"RFM_Validity/{axis}/B")
        if a is not None and b is not None:
            md[scale] = _num(a.text or "", path, f"{axis}/A")
            md[off] = _num(b.text or "", path, f"{axis}/B")
    return _dimap_shift(md, path, "dimap_v1")


#: RPC00A -> RPC00B term order: B[i] = A[_A_TO_B[i]]
_A_TO_B = [0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 7, 11, 12, 13, 14, 15, 16, 17, 18, 19]


@_register("ossim_geom")
def _read_geom(path: Path, text: str) -> RPC:
    kv: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            kv[key.strip().lower()] = value.strip()
    fmt = kv.get("polynomial_format", "B").upper()
    if fmt not in ("A", "B"):
        raise RPCError(f"{path}: polynomial_format {fmt!r} is neither A nor B")
    md: dict[str, object] = {}
    for key in _GDAL_KEYS:
        if key.lower() in kv:
            md[key] = _num(kv[key.lower()], path, key.lower())
    for key in _COEFF:
        found = {}
        for k, v in kv.items():
            m = re.fullmatch(key.lower() + r"_(\d+)", k)
            if m:
                found[int(m.group(1))] = _num(v, path, k)
        if found:
            if sorted(found) != list(range(len(found))):
                raise RPCError(f"{path}: {key.lower()}_ii indices are not 00..{len(found) - 1}")
            vals = [found[i] for i in sorted(found)]
            if fmt == "A" and len(vals) == 20:
                vals = [vals[i] for i in _A_TO_B]
            md[key] = vals
    return _build(md, path, "ossim_geom")


@_register("json")
def _read_json(path: Path, text: str) -> RPC:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UnsupportedFormatError(f"{path}: invalid JSON ({exc})") from exc
    rpc = doc.get("rpc", doc) if isinstance(doc, dict) else None
    if not isinstance(rpc, dict):
        raise UnsupportedFormatError(f"{path}: JSON has no 'rpc' object")
    names = {
        "row_offset": "LINE_OFF", "col_offset": "SAMP_OFF", "lat_offset": "LAT_OFF",
        "lon_offset": "LONG_OFF", "alt_offset": "HEIGHT_OFF", "row_scale": "LINE_SCALE",
        "col_scale": "SAMP_SCALE", "lat_scale": "LAT_SCALE", "lon_scale": "LONG_SCALE",
        "alt_scale": "HEIGHT_SCALE", "row_num": "LINE_NUM_COEFF", "row_den": "LINE_DEN_COEFF",
        "col_num": "SAMP_NUM_COEFF", "col_den": "SAMP_DEN_COEFF",
    }
    md = {gk: rpc[jk] for jk, gk in names.items() if jk in rpc}
    if not md:  # GDAL-style keys inside the JSON
        md = {k.upper(): v for k, v in rpc.items()}
    return _build(md, path, "json")


# ----------------------------------------------------------------- public API
def read_rpc(path: str | Path) -> RPC:
    """Read an RPC camera model from a file in any supported format.

    Parameters
    ----------
    path : str or Path
        RPC file or raster carrying RPC metadata (see module docstring).

    Returns
    -------
    RPC
        With ``source = "<path> (<format>)"``.

    Raises
    ------
    InputFileError
        The file does not exist or cannot be read.
    UnsupportedFormatError
        The content is no known RPC format.
    RPCError
        A known format with missing keys, wrong coefficient counts or
        non-finite/non-numeric values (the message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: no such file")
    try:
        text = _read_text(path)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc})") from exc
    fmt = detect_format(path, text)
    try:
        return READERS[fmt](path, text)
    except RPCError as exc:
        msg = str(exc)
        if str(path) not in msg:
            raise RPCError(f"{path}: {msg}") from exc
        raise
    except ET.ParseError as exc:  # pragma: no cover - detect_format parsed it already
        raise UnsupportedFormatError(f"{path}: malformed XML ({exc})") from exc


# -------------------------------------------------------------------- writers
#: units GDAL appends in its ``_RPC.TXT`` files (read back by GDAL and by :func:`read_rpc`)
_TXT_UNITS = {
    "LINE_OFF": "pixels", "SAMP_OFF": "pixels", "LAT_OFF": "degrees", "LONG_OFF": "degrees",
    "HEIGHT_OFF": "meters", "LINE_SCALE": "pixels", "SAMP_SCALE": "pixels", "LAT_SCALE": "degrees",
    "LONG_SCALE": "degrees", "HEIGHT_SCALE": "meters",
}


def format_rpc_txt(rpc: RPC) -> str:
    """GDAL's ``_RPC.TXT`` text of an RPC (``KEY: value unit`` lines, the
    coefficients as ``LINE_NUM_COEFF_1`` .. ``_20``), values at full double
    precision. Offsets follow the RPC standard (first pixel centre at 0), as
    GDAL expects."""
    md = rpc.to_gdal()
    lines = [f"{k}: {md[k]} {_TXT_UNITS[k]}" for k in _GDAL_KEYS]
    for key in _COEFF:
        lines += [f"{key}_{i}: {v}" for i, v in enumerate(md[key].split(), start=1)]
    return "\n".join(lines) + "\n"


def rpc_txt_path(image_path: str | Path) -> Path:
    """Where GDAL looks for an image's RPC text sidecar: ``<stem>_RPC.TXT``
    beside it."""
    p = Path(image_path)
    return p.with_name(p.stem + "_RPC.TXT")


def write_rpc_txt(rpc: RPC, path: str | Path) -> Path:
    """Write ``rpc`` as a GDAL ``_RPC.TXT`` file (atomically: a temporary
    sibling renamed into place). GDAL reads it as the camera of a raster
    ``<stem>.<ext>`` in the same folder when the file is named
    :func:`rpc_txt_path` of that raster.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(format_rpc_txt(rpc))
    tmp.replace(path)
    return path


def write_rpc_tags(path: str | Path, rpc: RPC) -> None:
    """Set the RPC of an existing GeoTIFF (opened ``r+`` by rasterio, which
    GDAL stores in the TIFF ``RPCCoefficientTag``), replacing any RPC it had.

    Raises
    ------
    InputFileError
        ``path`` is not a GeoTIFF GDAL can update.
    """
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError
    from rasterio.rpc import RPC as RioRPC

    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(path, "r+") as ds:
                if ds.driver != "GTiff":
                    raise InputFileError(f"{path}: RPC tags need a GeoTIFF, got a {ds.driver} raster")
                ds.rpcs = RioRPC.from_gdal(rpc.to_gdal())
    except RasterioIOError as exc:
        raise InputFileError(f"{path}: cannot open for update ({exc})") from exc


def crop_offset(image_path: str | Path) -> tuple[float, float] | None:
    """``(row0, col0)`` when the raster's geotransform is a pure pixel
    translation ``(1, 0, c0, 0, 1, r0)`` with no CRS (a crop of a larger
    image), else None."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(image_path) as ds:
            t, crs = ds.transform, ds.crs
    if crs is None and (t.a, t.b, t.d, t.e) == (1.0, 0.0, 0.0, 1.0):
        return float(t.f), float(t.c)
    return None


def _with_crop(rpc: RPC, image_path: Path) -> tuple[RPC, str]:
    off = crop_offset(image_path)
    if off is None or off == (0.0, 0.0):
        return rpc, ""
    return rpc.cropped(*off), f", cropped at row {off[0]:g}, col {off[1]:g} (geotransform)"


def find_camera(image_path: str | Path, rpc: str | Path | None = None) -> tuple[RPC, str]:
    """The RPC camera of an image, and where it came from.

    Order: the explicit ``rpc`` file; else the image's own RPC metadata read
    by GDAL (TIFF tags, NITF TRE); else a sidecar with the image's stem and
    one of :data:`SIDECAR_SUFFIXES` (``.geom``, ``.RPB``, ``_RPC.TXT``,
    ``.XML``...). GDAL itself picks up ``.RPB``/``_RPC.TXT``/DigitalGlobe
    ``.XML`` sidecars; they are reported as such.

    Crops: when the camera comes from a separate file (explicit or sidecar)
    and the image's geotransform is ``(1, 0, c0, 0, 1, r0)`` without CRS,
    the RPC describes the full image and the crop's RPC
    (``rpc.cropped(r0, c0)``) is returned.

    Returns
    -------
    (RPC, str)
        The camera and a human-readable description of its origin.

    Raises
    ------
    InputFileError
        ``image_path`` (or ``rpc``) does not exist.
    RPCError
        No camera was found (the message names the image and what was tried).
    """
    image_path = Path(image_path)
    if not image_path.exists():
        raise InputFileError(f"{image_path}: no such file")
    cam, origin = _find_camera(image_path, rpc)
    _check_image_in_domain(cam, origin, image_path)
    return cam, origin


#: the image centre localised this far outside the RPC's normalised ground domain [-1, 1] means offsets of
#: another image (the image coordinates themselves may lie anywhere: a crop keeps its full scene's scales)
_MAX_NORMALISED = 3.0


def _check_image_in_domain(cam: RPC, origin: str, image_path: Path) -> None:
    """Refuse an RPC that cannot localise the image's centre pixel inside
    (or near) the ground domain its polynomials were fitted on: its
    ``LINE_OFF``/``SAMP_OFF`` (or lat/lon offsets) belong to another image,
    and later steps would fail with only "did not converge"."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(image_path) as ds:
                height, width = ds.height, ds.width
    except rasterio.errors.RasterioIOError:
        return  # not this check's to report
    problem = f"{image_path}: its RPC ({origin}) does not describe this image's {height} x {width} pixels: "
    try:
        with np.errstate(all="ignore"):
            lon, lat = cam.localize(np.array([height / 2]), np.array([width / 2]), np.array([cam.height_off]))
    except RPCError:
        raise RPCError(problem + f"its centre pixel localises nowhere (LINE_OFF {cam.line_off:g}, SAMP_OFF "
                       f"{cam.samp_off:g}, LINE_SCALE {cam.line_scale:g}, SAMP_SCALE {cam.samp_scale:g}: offsets of "
                       "another image or crop?)") from None
    n_lat = (float(np.ravel(lat)[0]) - cam.lat_off) / cam.lat_scale
    n_lon = (float(np.ravel(lon)[0]) - cam.lon_off) / cam.lon_scale
    if not max(abs(n_lat), abs(n_lon)) <= _MAX_NORMALISED:
        raise RPCError(problem + f"its centre pixel localises at normalised lat {n_lat:.3g}, lon {n_lon:.3g}, far "
                       f"outside the [-1, 1] its polynomials describe (LINE_OFF {cam.line_off:g}, SAMP_OFF "
                       f"{cam.samp_off:g}: offsets of another image or crop?)")


def _find_camera(image_path: Path, rpc: str | Path | None) -> tuple[RPC, str]:
    """:func:`find_camera` before its check of the RPC's domain."""
    if rpc is not None:
        cam = read_rpc(rpc)
        origin = cam.source
        cam, crop = _with_crop(cam, image_path)
        return cam, f"explicit file {origin}{crop}"

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(image_path) as ds:
                rpcs, files, driver = ds.rpcs, [Path(f) for f in ds.files], ds.driver
    except RasterioIOError as exc:
        raise InputFileError(f"{image_path}: not a readable raster ({exc})") from exc
    if rpcs is not None:
        side = [f for f in files[1:] if f.name.upper().endswith((".RPB", "_RPC.TXT", ".XML"))
                and not f.name.upper().endswith(".AUX.XML")]
        if side:
            cam = _build({k.upper(): v for k, v in rpcs.to_dict().items()}, side[0], "gdal sidecar")
            cam, crop = _with_crop(cam, image_path)
            return cam, f"sidecar {side[0]} (read by GDAL){crop}"
        cam = _build({k.upper(): v for k, v in rpcs.to_dict().items()}, image_path, "gdal")
        return cam, f"RPC metadata of {image_path} ({driver} read by GDAL)"

    tried = []
    stem = image_path.with_suffix("")
    for suffix in SIDECAR_SUFFIXES:
        cand = stem.parent / (stem.name + suffix)
        if not cand.is_file() or cand == image_path:
            continue
        tried.append(cand.name)
        try:
            cam = read_rpc(cand)
        except UnsupportedFormatError:
            continue
        origin = cam.source
        cam, crop = _with_crop(cam, image_path)
        return cam, f"sidecar {origin}{crop}"
    what = f"; sidecars present but not RPC: {', '.join(tried)}" if tried else ""
    raise RPCError(
        f"{image_path}: no camera found (no RPC metadata in the file, no sidecar "
        f"{'/'.join(stem.name + s for s in SIDECAR_SUFFIXES[::2])}{what}); pass an explicit RPC file"
    )
