"""Side by side with a peer: CARS 1.3.0 and tiledsm on the s2p Pleiades pair.

Runs both tools on ``../shared/data/s2p_pair/input_pair`` (img_01.tif, img_02.tif, RPCs in the
TIFF tags) with 2 workers each, measures wall time and the peak memory of each process tree
(:mod:`benchmarks._measure`), compares each DSM with s2p's reference DSM
(``expected_output/pair/dsm.tif``, UTM 40S, 0.5 m, WGS84-ellipsoidal heights), prints a table and
writes ``benchmarks/results/peers.json``.

CARS lives in its own virtual environment (it pins its own numpy/rasterio/dask stack)::

    python3 -m venv /work/peers/cars && /work/peers/cars/bin/pip install cars==1.3.0

CARS configuration (CARS 1.3.0 schema, read from its ``pipelines/parameters`` modules):

- ``input.initial_elevation = {dem: flat_dem.tif}``: a DEM flat at 2320 m (WGS84-ellipsoidal)
  in EPSG:4326 covering both footprints. With no ``geoid`` key CARS reads DEM heights as EGM96
  heights and adds its internal EGM96 undulation N (``cars/conf/geoid/egm96.grd``; N = +1.85 m
  here), so the file stores ``2320 - N``: CARS then sees 2320 m above the ellipsoid. (CARS's
  default path, kept on purpose: ``geoid: null`` is accepted by its schema but is an untested
  path there.)
- ``output = {resolution: 0.5, epsg: 32740, geoid: false}``: ``geoid: false`` keeps the output
  heights on the ellipsoid (CARS's default, ``true``, writes EGM96 heights), so they compare
  directly with s2p's ellipsoidal reference and with tiledsm.
- ``orchestrator = {mode: multiprocessing, nb_workers: 2}``. Everything else is CARS's default
  (its coarse-to-fine resolutions; its DSM comes filled: the depth-to-Z fusion fills invalid
  matches and the rasterisation fills small holes, see :func:`cars_matched_only`, which gives
  a second, "matched cells only" row from the same run).

Metrics (identical code for both tools): the DSM is resampled (bilinear) onto the reference grid;
on the cells where the reference has a height, ``d = dsm - reference``;
``nmad = 1.4826 * median(|d - median(d)|)`` (metres); completeness = fraction of those cells with
a height. tiledsm's own ``metrics.json`` is kept alongside in the JSON.

Usage::

    .venv/bin/python benchmarks/peers.py [--only cars|tiledsm|both] [--cars PATH] [--reuse]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import Measurement, measure  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data" / "s2p_pair"
DEFAULT_CARS = Path("/work/peers/cars/bin/cars")
INSTALL_HINT = (
    "CARS 1.3.0 is installed in its own venv, outside the repository:\n"
    "    python3 -m venv /work/peers/cars && /work/peers/cars/bin/pip install cars==1.3.0\n"
    "then pass --cars /work/peers/cars/bin/cars or set TILEDSM_CARS_VENV=/work/peers/cars"
)

#: Figures quoted in issue 3 ("measured here for scale, on the full 1024x1024 pair on 2 cores");
#: not measured by this script.
QUOTED = [
    {"tool": "s2p (quoted, not measured here)", "wall_s": 47.0, "peak_rss_mib": 874.0, "nmad_m": 0.25, "completeness": 0.93},
    {"tool": "CARS (quoted, not measured here)", "wall_s": 180.0, "peak_rss_mib": 3.5 * 1024, "nmad_m": 0.37, "completeness": None},
]


# ----------------------------------------------------------------------------------------------
# locating the tools


def find_cars(explicit: str | None) -> Path | None:
    """The CARS executable: ``explicit``, else ``$TILEDSM_CARS_VENV/bin/cars``, else
    ``/work/peers/cars/bin/cars``; ``None`` when none exists."""
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    candidates = []
    if os.environ.get("TILEDSM_CARS_VENV"):
        candidates.append(Path(os.environ["TILEDSM_CARS_VENV"]) / "bin" / "cars")
    candidates.append(DEFAULT_CARS)
    return next((c for c in candidates if c.is_file()), None)


def find_tiledsm(explicit: str | None) -> Path | None:
    """The tiledsm executable: ``explicit``, else next to this Python, else on ``PATH``."""
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    here = Path(sys.executable).parent / "tiledsm"
    if here.is_file():
        return here
    found = shutil.which("tiledsm")
    return Path(found) if found else None


def venv_version(exe: Path, dist: str) -> str:
    """Version of distribution ``dist`` installed in the venv that holds ``exe`` (read from its
    ``DIST-VERSION.dist-info`` folder, no import), or ``"?"``."""
    for info in sorted((exe.parent.parent / "lib").glob(f"python3*/site-packages/{dist}-*.dist-info")):
        return info.name[len(dist) + 1 : -len(".dist-info")]
    return "?"


# ----------------------------------------------------------------------------------------------
# inputs for CARS


def footprint_lonlat(images: list[Path], height: float) -> tuple[float, float, float, float]:
    """Union of the image footprints at ``height`` (ellipsoidal m): (lon_min, lat_min, lon_max, lat_max), degrees.

    Corners are localised with GDAL's RPC transformer (through rasterio), outer pixel edges.
    """
    import rasterio
    from rasterio.transform import RPCTransformer

    lons, lats = [], []
    for path in images:
        with rasterio.open(path) as ds:
            rpcs, rows, cols = ds.rpcs, ds.height, ds.width
        if rpcs is None:
            raise SystemExit(f"{path}: no RPC tags; CARS and tiledsm both need RPCs here")
        with RPCTransformer(rpcs, rpc_height=height) as tr:
            x, y = tr.xy([0, 0, rows, rows], [0, cols, 0, cols], offset="ul")
        lons += list(np.atleast_1d(x))
        lats += list(np.atleast_1d(y))
    return min(lons), min(lats), max(lons), max(lats)


def write_flat_dem(path: Path, bounds: tuple[float, float, float, float], height: float, *, margin_deg: float = 0.01, step_deg: float = 0.0005) -> None:
    """A constant-height GeoTIFF in EPSG:4326 covering ``bounds`` plus ``margin_deg``.

    Parameters
    ----------
    path : Path
        Output file.
    bounds : (lon_min, lat_min, lon_max, lat_max)
        Degrees.
    height : float
        Metres (WGS84-ellipsoidal here: the CARS config sets ``geoid: null`` for it).
    margin_deg, step_deg : float
        Margin around the bounds and pixel size, degrees (0.0005 deg is about 50 m).
    """
    import rasterio
    from rasterio.transform import from_origin

    west, south = bounds[0] - margin_deg, bounds[1] - margin_deg
    east, north = bounds[2] + margin_deg, bounds[3] + margin_deg
    width, rows = math.ceil((east - west) / step_deg), math.ceil((north - south) / step_deg)
    profile = dict(driver="GTiff", width=width, height=rows, count=1, dtype="float32", crs="EPSG:4326", transform=from_origin(west, north, step_deg, step_deg))
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.full((1, rows, width), height, np.float32))


def cars_geoid_undulation(cars: Path, lon: float, lat: float) -> float:
    """EGM96 undulation N (m, geoid above ellipsoid) at (lon, lat) from the grid CARS ships.

    Bilinear in the 0.25-degree grid ``cars/conf/geoid/egm96.grd`` of the venv holding ``cars``.
    """
    import rasterio

    grids = sorted((cars.parent.parent / "lib").glob("python3*/site-packages/cars/conf/geoid/egm96.grd"))
    if not grids:
        raise SystemExit(f"{cars}: CARS's geoid grid cars/conf/geoid/egm96.grd was not found in its venv")
    with rasterio.open(grids[0]) as g:
        col, row = ~g.transform * (lon, lat)
        c0, r0 = int(math.floor(col - 0.5)), int(math.floor(row - 0.5))
        w = g.read(1, window=((r0, r0 + 2), (c0, c0 + 2))).astype(np.float64)
    fc, fr = col - 0.5 - c0, row - 0.5 - r0
    return float((w[0, 0] * (1 - fc) + w[0, 1] * fc) * (1 - fr) + (w[1, 0] * (1 - fc) + w[1, 1] * fc) * fr)


def cars_config(images: list[Path], dem: Path, out_dir: Path, *, resolution: float, epsg: int, workers: int) -> dict:
    """CARS 1.3.0 configuration (see the module docstring for the choices)."""
    return {
        "input": {
            "sensors": {"left": {"image": str(images[0])}, "right": {"image": str(images[1])}},
            "pairing": [["left", "right"]],
            "initial_elevation": {"dem": str(dem)},
        },
        "output": {"directory": str(out_dir), "resolution": resolution, "epsg": epsg, "geoid": False, "product_level": ["dsm"]},
        "orchestrator": {"mode": "multiprocessing", "nb_workers": workers},
    }


def find_cars_dsm(out_dir: Path) -> Path | None:
    """CARS's DSM in its output folder (``dsm/dsm.tif`` in 1.3; first ``*dsm*.tif`` otherwise)."""
    direct = out_dir / "dsm" / "dsm.tif"
    if direct.is_file():
        return direct
    hits = sorted(p for p in out_dir.rglob("dsm*.tif") if "dump_dir" not in p.parts)
    return hits[0] if hits else None


def cars_matched_only(out_dir: Path, dest: Path) -> Path | None:
    """CARS's DSM with the cells it did not match directly set to NaN, written to ``dest``.

    CARS 1.3's defaults fill its DSM: the anisotropic depth-to-Z fusion fills invalid matches and
    the rasterisation fills small holes (``fill_nodata: true``). Its auxiliary layers say where:
    ``dsm/filling.tif`` (1 = ``no_edition``, 3 = ``interpolation``, 0 = no data) and
    ``dsm/invalidity_mask.tif`` (0 = valid, 1-3 = dense-matching invalidity flags, 255 = no data).
    Kept here: ``filling == 1`` and ``invalidity_mask == 0``. ``None`` when a layer is missing.
    """
    import rasterio

    layers = [out_dir / "dsm" / n for n in ("dsm.tif", "filling.tif", "invalidity_mask.tif")]
    if not all(p.is_file() for p in layers):
        return None
    with rasterio.open(layers[0]) as src:
        dsm = src.read(1, masked=True).filled(np.nan).astype(np.float32)
        profile = src.profile | {"nodata": np.nan, "dtype": "float32"}
    with rasterio.open(layers[1]) as f, rasterio.open(layers[2]) as m:
        keep = (f.read(1) == 1) & (m.read(1) == 0)
    dsm[~keep] = np.nan
    with rasterio.open(dest, "w", **profile) as dst:
        dst.write(dsm, 1)
    return dest


# ----------------------------------------------------------------------------------------------
# evaluation


def compare_to_reference(dsm_path: Path, ref_path: Path) -> dict:
    """Statistics of ``dsm - reference`` on the reference grid.

    The DSM is resampled bilinearly onto the reference grid (rioxarray ``reproject_match``; NaN
    and the file's nodata are no-height); a reference cell has a DSM height only if the DSM cell
    containing its centre has one (so resampling does not fill holes). On aligned grids (same
    CRS and cell size, integer offset: the case for CARS and tiledsm here) this is an exact copy.
    Cells where the reference is NaN are ignored.

    Returns
    -------
    dict
        ``n_reference`` (cells with a reference height), ``n_valid`` (of those, cells with a DSM
        height), ``completeness`` (fraction), ``median_m``, ``mean_m``, ``nmad_m``
        (1.4826 x median absolute deviation from the median), ``rmse_m``, ``p99_abs_m``. Metres; ellipsoidal heights on both sides.
    """
    import rioxarray
    from rasterio.enums import Resampling

    ref = rioxarray.open_rasterio(ref_path, masked=True).squeeze("band", drop=True)
    dsm = rioxarray.open_rasterio(dsm_path, masked=True).squeeze("band", drop=True)
    if dsm.rio.crs is None:
        raise SystemExit(f"{dsm_path}: no CRS; cannot place it on the reference grid")
    bilinear = dsm.rio.reproject_match(ref, resampling=Resampling.bilinear, nodata=np.nan).values
    nearest = dsm.rio.reproject_match(ref, resampling=Resampling.nearest, nodata=np.nan).values
    # a cell counts as covered only if the DSM cell it falls in has a height: GDAL's bilinear
    # re-weights around nodata and would otherwise fill one-cell holes
    h = np.where(np.isfinite(nearest), bilinear, np.nan).astype(np.float64)
    r = ref.values.astype(np.float64)
    sel = np.isfinite(r)
    d = h[sel] - r[sel]
    d = d[np.isfinite(d)]
    out = {"n_reference": int(sel.sum()), "n_valid": int(d.size), "completeness": d.size / max(int(sel.sum()), 1)}
    if d.size:
        med = float(np.median(d))
        out.update(
            median_m=med,
            mean_m=float(d.mean()),
            nmad_m=float(1.4826 * np.median(np.abs(d - med))),
            rmse_m=float(np.sqrt(np.mean(d**2))),
            p99_abs_m=float(np.percentile(np.abs(d), 99)),
        )
    return out


# ----------------------------------------------------------------------------------------------
# runs


def _load_reused(run_dir: Path) -> dict | None:
    record = run_dir / "measurement.json"
    if record.is_file():
        rec = json.loads(record.read_text())
        if rec.get("returncode") == 0:
            return rec
    return None


def _measure_and_record(argv: list, run_dir: Path, timeout: float | None) -> dict:
    m: Measurement = measure(argv, cwd=run_dir, log=run_dir / "run.log", timeout=timeout)
    rec = m.to_dict() | {"when": _dt.datetime.now().isoformat(timespec="seconds")}
    (run_dir / "measurement.json").write_text(json.dumps(rec, indent=2))
    return rec


def _initial_elevation_record(cars: Path, dem: Path) -> dict:
    """What the flat DEM given to CARS holds: stored (EGM96) value, N, and the ellipsoidal height."""
    import rasterio

    with rasterio.open(dem) as src:
        stored = float(src.read(1)[0, 0])
        west, south, east, north = src.bounds
    n = cars_geoid_undulation(cars, (west + east) / 2, (south + north) / 2)
    return {"file": str(dem), "stored_egm96_m": stored, "egm96_undulation_m": n, "ellipsoidal_m": stored + n}


def run_cars(cars: Path, images: list[Path], reference: Path, run_dir: Path, args: argparse.Namespace) -> dict:
    """Run CARS once into ``run_dir`` (or reuse a finished run); return its row."""
    row = {"tool": f"CARS {venv_version(cars, 'cars')}"}
    run_dir.mkdir(parents=True, exist_ok=True)
    out_dir = run_dir / "out"
    rec = _load_reused(run_dir) if args.reuse else None
    if rec is None:
        if out_dir.exists():
            shutil.rmtree(out_dir)
        dem = run_dir / "flat_dem.tif"
        bounds = footprint_lonlat(images, args.dem_height)
        n = cars_geoid_undulation(cars, (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2)
        write_flat_dem(dem, bounds, args.dem_height - n)
        with __import__("rasterio").open(reference) as ref:
            epsg = ref.crs.to_epsg()
        config = cars_config(images, dem, out_dir, resolution=args.resolution, epsg=epsg, workers=args.workers)
        (run_dir / "config.json").write_text(json.dumps(config, indent=2))
        argv = [cars, run_dir / "config.json"]
        print(f"running: {' '.join(map(str, argv))}  (log: {run_dir / 'run.log'})", flush=True)
        rec = _measure_and_record(argv, run_dir, args.timeout)
    row["command"] = " ".join(map(str, rec["argv"]))
    row["measurement"] = rec
    row["initial_elevation"] = _initial_elevation_record(cars, run_dir / "flat_dem.tif")
    if rec["returncode"] != 0:
        row["error"] = f"CARS exited with status {rec['returncode']}{' (timeout)' if rec['timed_out'] else ''}; see {run_dir / 'run.log'}"
        return row
    dsm = find_cars_dsm(out_dir)
    if dsm is None:
        row["error"] = f"CARS finished but no DSM was found under {out_dir}"
        return row
    row["dsm"] = str(dsm)
    row["vs_reference"] = compare_to_reference(dsm, reference)
    matched = cars_matched_only(out_dir, run_dir / "dsm_matched_only.tif")
    if matched is not None:
        row["vs_reference_matched_only"] = compare_to_reference(matched, reference)
    return row


def run_tiledsm(tiledsm: Path, images: list[Path], reference: Path, run_dir: Path, args: argparse.Namespace) -> dict:
    """Run ``tiledsm dsm`` once into ``run_dir`` (or reuse a finished run); return its row."""
    import importlib.metadata

    try:
        version = importlib.metadata.version("tiledsm")
    except importlib.metadata.PackageNotFoundError:
        version = "?"
    row = {"tool": f"tiledsm {version}"}
    run_dir.mkdir(parents=True, exist_ok=True)
    out_dir = run_dir / "out"
    rec = _load_reused(run_dir) if args.reuse else None
    if rec is None:
        if out_dir.exists():
            shutil.rmtree(out_dir)
        # scored below (compare_to_reference), as the peers are: the timed command only makes the DSM
        argv = [tiledsm, "dsm", *images, "--out", out_dir, "--like", reference, "--workers", str(args.workers)]
        print(f"running: {' '.join(map(str, argv))}  (log: {run_dir / 'run.log'})", flush=True)
        rec = _measure_and_record(argv, run_dir, args.timeout)
    row["command"] = " ".join(map(str, rec["argv"]))
    row["measurement"] = rec
    if rec["returncode"] != 0:
        tail = (run_dir / "run.log").read_text(errors="replace").strip().splitlines()[-5:]
        row["error"] = f"tiledsm exited with status {rec['returncode']}; see {run_dir / 'run.log'}: " + " | ".join(tail)
        return row
    metrics = out_dir / "metrics.json"
    if metrics.is_file():
        row["metrics_json"] = json.loads(metrics.read_text())
    dsm = out_dir / "dsm.tif"
    if not dsm.is_file():
        row["error"] = f"tiledsm finished but {dsm} is missing"
        return row
    row["dsm"] = str(dsm)
    row["vs_reference"] = compare_to_reference(dsm, reference)
    return row


# ----------------------------------------------------------------------------------------------
# report


def _summary(row: dict) -> dict:
    m = row.get("measurement") or {}
    v = row.get("vs_reference") or {}
    return {
        "tool": row["tool"],
        "wall_s": row.get("wall_s", m.get("wall_s")),
        "peak_rss_mib": row.get("peak_rss_mib", m.get("peak_rss_mib")),
        "peak_pss_mib": m.get("peak_pss_mib"),
        # CPU seconds of the tree; records made before _measure sampled CPU only have getrusage's
        # figure, which misses forkserver workers (CARS), so they show none
        "cpu_s": m.get("cpu_s_sampled") and m.get("cpu_s"),
        "nmad_m": row.get("nmad_m", v.get("nmad_m")),
        "median_m": v.get("median_m"),
        "completeness": row.get("completeness", v.get("completeness")),
        "error": row.get("error"),
    }


def format_table(rows: list[dict], base: dict | None) -> str:
    """Plain-text table; ratios are ``tool / tiledsm`` (time and peak RSS)."""

    def f(v, fmt):
        return "-".rjust(int(fmt.split(".")[0])) if v is None else format(v, fmt)

    head = f"{'tool':34} {'wall s':>8} {'CPU s':>7} {'RSS MiB':>8} {'PSS MiB':>8} {'NMAD m':>7} {'bias m':>7} {'compl %':>8} {'t/tiledsm':>9} {'mem/tiledsm':>11}"
    lines = [head, "-" * len(head)]
    for r in rows:
        s = _summary(r)
        rt = rm = None
        if base and base.get("wall_s") and s["wall_s"] is not None and not s["error"]:
            rt = s["wall_s"] / base["wall_s"]
            rm = s["peak_rss_mib"] / base["peak_rss_mib"] if s["peak_rss_mib"] and base.get("peak_rss_mib") else None
        compl = None if s["completeness"] is None else 100 * s["completeness"]
        lines.append(
            f"{s['tool'][:34]:34} {f(s['wall_s'], '8.1f')} {f(s['cpu_s'], '7.1f')} {f(s['peak_rss_mib'], '8.0f')} {f(s['peak_pss_mib'], '8.0f')} "
            f"{f(s['nmad_m'], '7.3f')} {f(s['median_m'], '7.2f')} {f(compl, '8.1f')} {f(rt, '9.2f')} {f(rm, '11.2f')}"
        )
        if s["error"]:
            lines.append(f"    FAILED: {s['error']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", choices=("cars", "tiledsm", "both"), default="both")
    p.add_argument("--cars", default=None, help="CARS executable (default: $TILEDSM_CARS_VENV/bin/cars or /work/peers/cars/bin/cars)")
    p.add_argument("--tiledsm", default=None, help="tiledsm executable (default: next to this Python)")
    p.add_argument("--data", type=Path, default=DATA, help="the s2p_pair folder (default: ../shared/data/s2p_pair)")
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "peers", help="run folders (default: runs/peers)")
    p.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "peers.json")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--resolution", type=float, default=0.5, help="CARS DSM cell size, m")
    p.add_argument("--dem-height", type=float, default=2320.0, help="flat initial DEM for CARS, ellipsoidal m")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per tool")
    p.add_argument("--reuse", action="store_true", help="reuse a finished run in the run folder instead of running again")
    args = p.parse_args(argv)

    images = [args.data / "input_pair" / "img_01.tif", args.data / "input_pair" / "img_02.tif"]
    reference = args.data / "expected_output" / "pair" / "dsm.tif"
    missing = [str(x) for x in [*images, reference] if not x.is_file()]
    if missing:
        print(f"peers.py: missing input data: {', '.join(missing)}", file=sys.stderr)
        return 2

    cars = tiledsm = None
    if args.only in ("cars", "both"):
        cars = find_cars(args.cars)
        if cars is None:
            print(f"peers.py: CARS not found ({args.cars or 'default locations'}).\n{INSTALL_HINT}", file=sys.stderr)
            return 2
    if args.only in ("tiledsm", "both"):
        tiledsm = find_tiledsm(args.tiledsm)
        if tiledsm is None:
            print("peers.py: the tiledsm executable was not found; run `make install` or pass --tiledsm PATH", file=sys.stderr)
            return 2

    rows: list[dict] = []
    base = None
    if tiledsm is not None:
        rows.append(run_tiledsm(tiledsm, images, reference, args.runs / "tiledsm", args))
        base = None if rows[-1].get("error") else _summary(rows[-1])
    if cars is not None:
        rows.append(run_cars(cars, images, reference, args.runs / "cars", args))
        if "vs_reference_matched_only" in rows[-1]:
            rows.append(
                {
                    "tool": rows[-1]["tool"] + ", matched cells only",
                    "derived_from": rows[-1]["tool"],
                    "note": "same run; CARS's filled cells (filling.tif != 1) and invalid matches (invalidity_mask.tif != 0) set to no height",
                    "measurement": rows[-1]["measurement"],
                    "vs_reference": rows[-1]["vs_reference_matched_only"],
                }
            )
    quoted = [dict(q) for q in QUOTED]

    print()
    print(f"s2p_pair (1024x1024 + 1031x1102 px Pleiades), {args.workers} workers, DSM vs s2p reference ({reference.name}, ellipsoidal)")
    print(format_table(rows + quoted, base))
    print("NMAD/bias: DSM minus s2p reference on the reference grid (m); completeness: share of reference cells with a height.")
    print("RSS: peak of the summed RSS of the process tree; PSS: the same with shared pages split (closer to real RAM).")
    print("CPU: user+system seconds of the whole tree. Wall times depend on the machine's load: see load_before/after in the JSON.")

    result = {
        "benchmark": "peers",
        "when": _dt.datetime.now().isoformat(timespec="seconds"),
        "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "data": str(args.data),
        "reference": str(reference),
        "workers": args.workers,
        "cars_settings": {"dem_height_m": args.dem_height, "heights": "WGS84 ellipsoidal (flat DEM stored as 2320 - N(EGM96) for CARS's default geoid; output.geoid false)", "resolution_m": args.resolution},
        "rows": [r | {"summary": _summary(r)} for r in rows],
        "quoted_not_measured": quoted,
        "ratios_to_tiledsm": {
            r["tool"]: {"wall": _summary(r)["wall_s"] / base["wall_s"], "peak_rss": _summary(r)["peak_rss_mib"] / base["peak_rss_mib"]}
            for r in rows
            if base and not r.get("error") and _summary(r)["wall_s"]
        },
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        previous = json.loads(args.json.read_text()) if args.json.is_file() else {}
        if args.only != "both" and previous.get("rows"):
            # keep the other tool's last rows so a partial re-run does not erase them
            keep = [r for r in previous["rows"] if r["tool"].split()[0] not in {n["tool"].split()[0] for n in rows}]
            result["rows"] = keep + result["rows"]
        args.json.write_text(json.dumps(result, indent=2, default=str))
        print(f"wrote {args.json}")
    return 1 if any(r.get("error") for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
