"""Orientation (issue 10): bias-compensated RPC block adjustment, measured.

Run: ``.venv/bin/python benchmarks/orient.py`` (about 3 minutes on 2 cores); writes
``benchmarks/results/orient.json`` and prints a table.

Cases
-----
synthetic (``make_scene``, 512 px, GSD 0.5 m, B/H 0.4, 2 and 3 views). Biases injected per view
(``tests/orient/orient_cases.py`` BIASES: |A0|, |B0| 2-3 px, every linear term 1e-4) into copies of
the views (RPC tags). Truth: the scene's own RPCs and truth DSM.

- ``gcp4``: 4 GCPs near the image corners (0.05 px measurement noise, exact ground) + tie points;
  check = RMS over 300 random ground points of |corrected RPC - true RPC| in each view (px),
  and the RMS at 20 held-out check points as the stage reports it.
- ``ties``: tie points only; "relative" = RMS reprojection residual of *true* correspondences
  (300 random ground points projected by the true RPCs) intersected with the corrected RPCs.
- ``dem`` (2 views): no GCP, the reference DEM is the truth DSM block-averaged to 8 m cells
  (16 px) and, as ``dem_32m``, to 32 m cells (64 px: SRTM's 30 m over a 0.5 m GSD scene, 8 cells
  across it); DSM (``tiledsm dsm --like truth``) minus truth, median over the visible mask, with
  the biased and with the corrected RPCs. A coarse cell averages buildings with the ground beside
  them, so DEM-minus-point errors are skewed; the adjustment weights points by the DEM's slope and
  re-estimates the DEM's sigma robustly (``tiledsm.orient.adjust``; before that fix: 0.337 m at 8 m).
- ``p2l``: 1000 synthetic matches, 20 % blunders (half displaced 5-50 px, half anywhere in
  image 2), 0.2 px noise, biased cameras: share of blunders caught / good matches kept, P2L vs
  OpenCV RANSAC on a fundamental matrix (1 px).

real
- Ventoux (``shareloc_phr_ventoux``): left + right crops with their OSSIM ``.geom`` RPCs (crop offsets
  from the geotransforms), DEM = SRTM N44E005 + EGM96. Two right cameras: the vendor one and
  ``right_image_bias.geom`` (``line_off`` + 60). DSM - (SRTM + EGM96) median over the DSM's cells,
  before and after DEM-assisted adjustment (no GCP).
- s2p pair: tie points only; relative RMS (multi-view intersection residual of the tie points)
  before and after.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "orient"))
sys.path.insert(0, str(ROOT))

from orient_cases import BIASES, relative_error  # noqa: E402

from tiledsm.cli import main  # noqa: E402
from tiledsm.io.cameras import find_camera  # noqa: E402
from tiledsm.orient import OrientSpec, ReferenceDEM, orient_images, write_orientation  # noqa: E402
from tiledsm.orient.p2l import p2l_filter, ransac_filter  # noqa: E402
from simulate import (  # noqa: E402
    biased_copies, corner_points, ground_points, project_all, write_points_csv,
)

SHARED = ROOT.parent / "shared" / "data"
WORK = ROOT / "runs" / "bench_orient"


def _rms(d):
    return float(np.sqrt(np.mean(np.sum(np.asarray(d) ** 2, axis=-1))))


def _dsm_bias(images, out, like=None, ref_fn=None, mask=None, truth=None):
    """Median DSM - reference over valid cells: ``truth`` raster (with ``mask``) or ``ref_fn(lon, lat)``."""
    import rasterio
    from pyproj import Transformer

    args = ["dsm", *map(str, images), "--out", str(out), "--scheduler", "synchronous", "--no-progress", "--overwrite"]
    if like:
        args += ["--like", str(like)]
    assert main(args) == 0
    with rasterio.open(out / "dsm.tif") as ds:
        z = ds.read(1)
        if truth is not None:
            with rasterio.open(truth) as t, rasterio.open(mask) as m:
                d = (z - t.read(1))[m.read(1) == 1]
        else:
            ii, jj = np.nonzero(np.isfinite(z))
            x, y = ds.transform * (jj + 0.5, ii + 0.5)
            lon, lat = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True).transform(x, y)
            d = z[ii, jj] - ref_fn(lon, lat)
    d = d[np.isfinite(d)]
    return {"median_m": float(np.median(d)), "nmad_m": float(1.4826 * np.median(np.abs(d - np.median(d)))),
            "n": int(d.size)}


def synthetic(views: int) -> dict:
    from tiledsm.synth import make_scene

    root = WORK / f"synth{views}"
    info = make_scene(root / "scene", size=512, views=views, seed=4, chunk=256)
    true = [find_camera(p)[0] for p in info.views]
    h = (true[0].height_off - true[0].height_scale, true[0].height_off + true[0].height_scale)
    biased = biased_copies(info.views, true, BIASES[:views], root / "biased", h)
    names = [p.name for p in biased]
    shape = (512, 512)
    gl, ga, gh = corner_points(true[0], shape, (300, 400), seed=1)
    write_points_csv(root / "gcps.csv", names, true, gl, ga, gh, noise_px=0.05, shape=shape)
    cl, ca, ch = ground_points(true[0], shape, (300, 400), 20, seed=2)
    write_points_csv(root / "checks.csv", names, true, cl, ca, ch, prefix="c", shape=shape)
    lon, lat, hh = ground_points(true[0], shape, (300, 400), 300, seed=3)
    spec = OrientSpec(tile=256)
    out = {}
    before_rel = relative_error([find_camera(p)[0] for p in biased], true, lon, lat, hh)
    for case, gcps in (("gcp4", root / "gcps.csv"), ("ties", None)):
        t0 = time.perf_counter()
        o = orient_images(biased, gcps, root / "checks.csv", spec=spec)
        write_orientation(o, root / f"out_{case}", spec)
        t = time.perf_counter() - t0
        vs_true = [_rms(np.stack(a.project(lon, lat, hh), -1) - np.stack(b.project(lon, lat, hh), -1))
                   for a, b in zip(o.rpcs_after, true)]
        vs_true_before = [_rms(np.stack(a.project(lon, lat, hh), -1) - np.stack(b.project(lon, lat, hh), -1))
                          for a, b in zip(o.rpcs_before, true)]
        out[case] = {
            "vs_true_rpc_px": {"before": vs_true_before, "after": vs_true},
            "check_rms_px": o.report["check_rms_px"], "tie_relative_rms_px": o.report["tie_relative_rms_px"],
            "relative_truth_px": {"before": before_rel, "after": relative_error(list(o.rpcs_after), true, lon, lat, hh)},
            "n_tracks": o.report["n_tracks"], "views_per_track": o.report["tracks"]["views_per_track"],
            "models": [m.name for m in o.models], "seconds": t,
        }
    if views == 2:
        # reference DEM: the truth DSM block-averaged to k x k cells
        import rasterio
        from rasterio.transform import Affine

        kw = dict(like=info.truth_dsm, truth=info.truth_dsm, mask=info.visible_mask)
        before = {"true_rpcs": _dsm_bias(info.views, root / "dsm_true", **kw),
                  "before": _dsm_bias(biased, root / "dsm_before", **kw)}
        for case, k in (("dem", 16), ("dem_32m", 64)):
            with rasterio.open(info.truth_dsm) as ds:
                z = ds.read(1)
                zz = z.reshape(z.shape[0] // k, k, z.shape[1] // k, k).mean(axis=(1, 3))
                prof = dict(driver="GTiff", width=zz.shape[1], height=zz.shape[0], count=1, dtype="float32",
                            crs=ds.crs, transform=ds.transform @ Affine.scale(k))
                gsd = abs(ds.transform.a)
            dem_path = root / f"ref_dem_{k * gsd:g}m.tif"
            with rasterio.open(dem_path, "w", **prof) as d:
                d.write(zz.astype(np.float32), 1)
            lonr, latr = true[0].ground_box((0, 512, 0, 512), h)
            dem = ReferenceDEM.open(dem_path, lonr, latr)
            o = orient_images(biased, None, root / "checks.csv", dem=dem, spec=spec)
            write_orientation(o, root / f"out_{case}", spec)
            out[case] = {
                "dem_cell_m": k * gsd,
                "dsm_minus_truth": {**before, "after": _dsm_bias([root / f"out_{case}" / n for n in names],
                                                                 root / f"dsm_after_{case}", **kw)},
                "check_rms_px": o.report["check_rms_px"], "dem_used": o.report["dem"]["n_used"],
                "dem_sigma_m": o.report["adjustment"].get("dem_sigma_m"),
            }
    return out


def p2l_case() -> dict:
    from simulate import inject_bias, pushbroom_rpcs

    size, hr = 1024, (200.0, 400.0)
    true = pushbroom_rpcs(2, size, h_range=hr)
    biased = [inject_bias(r, a, b, (size, size), hr) for r, (a, b) in zip(true, BIASES)]
    rng = np.random.default_rng(0)
    n = 1000
    lon, lat, h = ground_points(true[0], (size, size), hr, n, seed=1)
    p = project_all(true, lon, lat, h) + rng.normal(0, 0.2, (2, n, 2))
    bl = rng.random(n) < 0.2
    local = bl & (rng.random(n) < 0.5)
    ang, mag = rng.uniform(0, 2 * np.pi, n), rng.uniform(5, 50, n)
    p[1, local] += (np.column_stack([np.cos(ang), np.sin(ang)]) * mag[:, None])[local]
    p[1, bl & ~local] = rng.uniform(0, size, (int((bl & ~local).sum()), 2))
    r = p2l_filter(biased[0], biased[1], p[0], p[1], hr)
    out = {"n": n, "blunders": int(bl.sum()), "p2l": {"caught": float(np.mean(~r.inlier[bl])),
           "caught_local": float(np.mean(~r.inlier[local])), "kept": float(np.mean(r.inlier[~bl])),
           "threshold_px": r.threshold_px}}
    for thr in (1.0, 2.0):
        m = ransac_filter(p[0], p[1], thr)
        out[f"ransac_{thr:g}px"] = {"caught": float(np.mean(~m[bl])), "caught_local": float(np.mean(~m[local])),
                                    "kept": float(np.mean(m[~bl]))}
    return out


def ventoux() -> dict:
    from tiledsm.orient.export import copy_with_rpc

    d = SHARED / "shareloc_phr_ventoux"
    root = WORK / "ventoux"
    root.mkdir(parents=True, exist_ok=True)
    geoid = d / "geoid" / "egm96_15.gtx"
    left, right = d / "left_image.tif", d / "right_image.tif"
    rl = find_camera(left)[0]
    out = {}
    for case, geom in (("vendor", d / "right_image.geom"), ("bias_line_off_60", d / "right_image_bias.geom")):
        rr = find_camera(right, rpc=geom)[0]
        src = root / case / "input"
        src.mkdir(parents=True, exist_ok=True)
        copy_with_rpc(left, src / "left_image.tif", rl)
        copy_with_rpc(right, src / "right_image.tif", rr)
        imgs = [src / "left_image.tif", src / "right_image.tif"]
        lonr, latr = rl.ground_box((0, 500, 0, 500), (300, 700))
        dem = ReferenceDEM.open(d / "srtm" / "N44E005.hgt", (lonr[0] - 0.02, lonr[1] + 0.02),
                                (latr[0] - 0.02, latr[1] + 0.02), geoid=geoid)
        spec = OrientSpec(tile=256)
        t0 = time.perf_counter()
        o = orient_images(imgs, dem=dem, spec=spec)
        write_orientation(o, root / case / "out", spec)
        t = time.perf_counter() - t0
        out[case] = {
            "terms": [dict(x) for x in o.terms], "models": [m.name for m in o.models],
            "tie_relative_rms_px": o.report["tie_relative_rms_px"], "n_tracks": o.report["n_tracks"],
            "dem_median_h_minus_dem_m": o.report["dem"]["median_h_minus_dem_m"], "seconds": t,
            "dsm_minus_srtm": {"before": _dsm_bias(imgs, root / case / "dsm_before", ref_fn=dem),
                               "after": _dsm_bias([root / case / "out" / p.name for p in imgs],
                                                  root / case / "dsm_after", ref_fn=dem)},
        }
    return out


def s2p() -> dict:
    d = SHARED / "s2p_pair" / "input_pair"
    imgs = [d / "img_01.tif", d / "img_02.tif"]
    spec = OrientSpec(tile=512)
    t0 = time.perf_counter()
    o = orient_images(imgs, spec=spec)
    write_orientation(o, WORK / "s2p" / "out", spec)
    return {"tie_relative_rms_px": o.report["tie_relative_rms_px"], "n_tracks": o.report["n_tracks"],
            "terms": [dict(x) for x in o.terms], "models": [m.name for m in o.models],
            "rejected": o.report["n_rejected"], "rejected_p2l": o.report["tracks"]["rejected_p2l"],
            "seconds": time.perf_counter() - t0}


def main_() -> None:
    import dask

    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    with dask.config.set(scheduler="threads", num_workers=2):
        res = {"command": ".venv/bin/python benchmarks/orient.py", "p2l": p2l_case(),
               "synthetic_2views": synthetic(2), "synthetic_3views": synthetic(3)}
        if SHARED.exists():
            res["ventoux"] = ventoux()
            res["s2p"] = s2p()
    res["total_s"] = time.perf_counter() - t0
    path = ROOT / "benchmarks" / "results" / "orient.json"
    path.write_text(json.dumps(res, indent=2))
    _table(res)


def _f(v, n=3):
    return "-" if v is None else (f"{v:.{n}f}" if isinstance(v, float) else str(v))


def _table(r: dict) -> None:
    p = r["p2l"]
    print(f"P2L vs RANSAC ({p['n']} matches, {p['blunders']} blunders): caught / caught local / good kept")
    print(f"  P2L          {_f(p['p2l']['caught'])} / {_f(p['p2l']['caught_local'])} / {_f(p['p2l']['kept'])}")
    for k in ("ransac_1px", "ransac_2px"):
        print(f"  {k:<12} {_f(p[k]['caught'])} / {_f(p[k]['caught_local'])} / {_f(p[k]['kept'])}")
    print("\nsynthetic               case   vs true RPC px before -> after          check px    relative px (truth)")
    for v in (2, 3):
        s = r[f"synthetic_{v}views"]
        for case in ("gcp4", "ties"):
            c = s[case]
            vt = ", ".join(f"{a:.2f}->{b:.3f}" for a, b in zip(c["vs_true_rpc_px"]["before"], c["vs_true_rpc_px"]["after"]))
            print(f"  {v} views  {case:<6} {vt:<42} {_f(c['check_rms_px']['before'], 2)}->{_f(c['check_rms_px']['after'])}"
                  f"   {_f(c['relative_truth_px']['before'], 2)}->{_f(c['relative_truth_px']['after'])}")
    for case in ("dem", "dem_32m"):
        c = r["synthetic_2views"][case]
        dm = c["dsm_minus_truth"]
        print(f"  2 views  {case:<7} ({c['dem_cell_m']:g} m cells) DSM - truth median: true RPCs "
              f"{dm['true_rpcs']['median_m']:.3f} m, biased {dm['before']['median_m']:.3f} m -> corrected "
              f"{dm['after']['median_m']:.3f} m")
    if "ventoux" in r:
        print("\nVentoux (DEM-assisted, SRTM+EGM96)   DSM - SRTM median before -> after     A0 of right image")
        for case, c in r["ventoux"].items():
            print(f"  {case:<20} {c['dsm_minus_srtm']['before']['median_m']:8.2f} m -> {c['dsm_minus_srtm']['after']['median_m']:6.2f} m"
                  f"      {c['terms'][1]['A0']:.2f} px (left {c['terms'][0]['A0']:.2f})")
        s = r["s2p"]
        print(f"\ns2p pair (ties only): relative RMS {s['tie_relative_rms_px']['before']:.3f} -> "
              f"{s['tie_relative_rms_px']['after']:.3f} px, {s['n_tracks']} tracks")
    print(f"\ntotal {r['total_s']:.0f} s")


if __name__ == "__main__":
    main_()
