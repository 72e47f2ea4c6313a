"""Tie-point extractors (issue 10): the feature path against structural matching, measured.

Run: ``nice -n 10 .venv/bin/python benchmarks/tiepoints.py`` (about a minute on 2 cores); writes
``benchmarks/results/tiepoints.json`` and prints a markdown table.

Cases: synthetic scenes (``tiledsm.synth.make_scene``, 1024 px, GSD 0.5 m, B/H 0.4, seeds 4, 5
and 6; figures per scene in the JSON, pooled in the table) with 2 and 3 views, written to a
temporary folder; every view gets the biases of
``tests/orient/orient_cases.py`` (2-3 px shifts, 1e-4 scale/shear) in its RPC tags, as the
orientation stage sees real images. ``tie_point_tracks`` (tiles of 512 px, one coarse guide per
scene shared by both extractors, synchronous scheduler) runs once per extractor
(``OrientSpec.extractor``: ``features`` = Shi-Tomasi + NCC segment search, ``structural`` =
Wallis + Förstner + NCC along the RPC curve + probability relaxation), each with its defaults.

Truth: the reference point's line of sight (true RPC of view 0) is intersected with the truth DSM
(bilinear, first crossing from above, 0.05 m steps) and the ground point projected into each
other view with its true RPC. A match is correct when it lies within ``tol`` px of that
projection (1 px in the table; 0.5 and 2 px in the JSON), pooled over the other views. Rays that
leave the truth grid (near the image borders) are left out of the score (``matches`` counts the
scored ones). Occluded points and points whose template straddles a wall or roof border count as
they come; "clear" scores only the matches whose ground point is seen by the view and has no edge
cell (``edge.tif``) within 8 cells (the template's half-width): there area matching has no
ambiguity, elsewhere it tends to follow the strongest edge (a roof border's parallax for a point
on the ground beside it). Times: wall seconds of ``tie_point_tracks`` without the coarse guide.

Orientation: ``benchmarks/orient.py``'s synthetic cases (512 px, tiles of 256) oriented with each
extractor's tie points: corrected vs true RPCs with 4 GCPs, relative error (truth) with ties only.

Real pairs (when ``../shared/data`` exists; no truth): the s2p Pleiades pair (1024 px, tiles of
512) and the Ventoux crops (500 px, vendor ``.geom`` RPCs, tiles of 256): tracks, P2L rejections,
and the relative RMS (px) of the tie points after a ties-only bias adjustment (``orient_images``):
a consistency figure, not a truth.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "orient"))
sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared" / "data"
TOLS = (0.5, 1.0, 2.0)


def _apply(aff, x, y):
    """``aff * (x, y)`` of an ``affine.Affine`` on arrays."""
    return aff.a * x + aff.b * y + aff.c, aff.d * x + aff.e * y + aff.f


def true_positions(ref_pos: np.ndarray, true_rpcs, scene_dir, step_m: float = 0.05,
                   clear_cells: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Truth of reference points ``ref_pos`` (``(n, 2)`` GDAL row/col in view 0) of a
    ``make_scene`` folder.

    The view-0 ray (true RPC) meets the truth DSM (bilinear between cell centres, first crossing
    from above, ``step_m`` steps refined linearly); the ground point is projected by each true
    RPC.

    Returns
    -------
    (pos, clear) : (numpy.ndarray, numpy.ndarray)
        ``(n_images, n, 2)`` true GDAL row/col (``pos[0] = ref_pos``; NaN where the ray misses
        the DSM) and ``(n_images, n)`` bool: the hit cell is seen by that view
        (``visible_{k}.tif``) and no edge cell (``edge.tif``: walls, roof and crown borders) lies
        within ``clear_cells`` cells of it, i.e. the template sees one smooth surface.
    """
    import rasterio
    from pyproj import Transformer
    from scipy.ndimage import binary_dilation, map_coordinates

    scene = Path(scene_dir)
    with rasterio.open(scene / "truth_dsm.tif") as ds:
        z = ds.read(1).astype(np.float64)
        inv = ~ds.transform
        to_xy = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True)
    with rasterio.open(scene / "edge.tif") as ds:
        near_edge = binary_dilation(ds.read(1) == 1, np.ones((2 * clear_cells + 1,) * 2, bool))
    zmin, zmax = np.nanmin(z) - 1.0, np.nanmax(z) + 1.0
    nodes = np.linspace(zmin, zmax, max(3, int(np.ceil((zmax - zmin) / 5.0)) + 1))
    n = len(ref_pos)
    out = np.full((len(true_rpcs), n, 2), np.nan)
    clear = np.zeros((len(true_rpcs), n), bool)
    out[0] = ref_pos
    if n == 0:
        return out, clear
    lon, lat = true_rpcs[0].localize(ref_pos[:, 0:1], ref_pos[:, 1:2], nodes[None])
    x, y = to_xy.transform(lon, lat)
    hs = np.arange(zmax, zmin, -step_m)  # from the top down
    fx = np.stack([np.interp(hs, nodes, x[i]) for i in range(n)])
    fy = np.stack([np.interp(hs, nodes, y[i]) for i in range(n)])
    col, row = _apply(inv, fx, fy)
    f = hs[None] - map_coordinates(z, [row - 0.5, col - 0.5], order=1, mode="constant", cval=np.nan)
    below = f <= 0
    first = np.argmax(below, axis=1)
    ar = np.arange(n)
    hit = below[ar, first] & (first > 0)
    i = np.clip(first, 1, len(hs) - 1)
    fa, fb = f[ar, i - 1], f[ar, i]
    h = np.where(hit, hs[i - 1] + (hs[i] - hs[i - 1]) * fa / (fa - fb), nodes[0])
    lo = np.array([np.interp(h[j], nodes, lon[j]) for j in range(n)])
    la = np.array([np.interp(h[j], nodes, lat[j]) for j in range(n)])
    hx, hy = to_xy.transform(lo, la)
    hc, hr = _apply(inv, hx, hy)
    ci = (np.clip(np.floor(np.nan_to_num(hr)).astype(int), 0, z.shape[0] - 1),
          np.clip(np.floor(np.nan_to_num(hc)).astype(int), 0, z.shape[1] - 1))
    for k, r in enumerate(true_rpcs):
        if k:
            out[k] = np.where(hit[:, None], np.column_stack(r.project(lo, la, h)), np.nan)
        with rasterio.open(scene / f"visible_{k}.tif") as ds:
            clear[k] = hit & (ds.read(1)[ci] == 1) & ~near_edge[ci]
    return out, clear


def errors(pos: np.ndarray, truth: np.ndarray, clear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (px) of the matches (observations outside the reference) with a truth, pooled
    over the other views, and whether each is ``clear``."""
    m = np.isfinite(pos[1:, :, 0]) & np.isfinite(truth[1:, :, 0])
    return np.hypot(*(pos[1:] - truth[1:])[m].T), clear[1:][m]


def summarise(err: np.ndarray, ok: np.ndarray, tols=TOLS) -> dict:
    """Matches, the share within each tolerance of the truth (all, and the clear ones) and the
    median error (px)."""
    out = {"matches": int(err.size), "clear_matches": int(ok.sum()),
           "median_error_px": float(np.median(err)) if err.size else None}
    for t in tols:
        out[f"correct_{t:g}px"] = float(np.mean(err < t)) if err.size else None
        out[f"correct_clear_{t:g}px"] = float(np.mean(err[ok] < t)) if ok.any() else None
    return out


def score(pos: np.ndarray, truth: np.ndarray, clear: np.ndarray, tols=TOLS) -> dict:
    """:func:`summarise` of :func:`errors`."""
    return summarise(*errors(pos, truth, clear), tols=tols)


EXTRACTORS = ("features", "structural")
SEEDS = (4, 5, 6)


def run_scene(views: int, seed: int, root: Path) -> tuple[dict, dict]:
    """One synthetic scene, both extractors: (JSON record, raw errors per extractor)."""
    from orient_cases import BIASES

    from tiledsm.io.cameras import find_camera
    from simulate import biased_copies
    from tiledsm.orient.spec import OrientSpec
    from tiledsm.orient.tracks import coarse_guide, tie_point_tracks
    from tiledsm.synth import make_scene

    info = make_scene(root / "scene", size=1024, views=views, seed=seed, chunk=512, workers=1)
    true = [find_camera(p)[0] for p in info.views]
    h = (true[0].height_off - true[0].height_scale, true[0].height_off + true[0].height_scale)
    biased = biased_copies(info.views, true, BIASES[:views], root / "biased", h)
    rpcs = [find_camera(p)[0] for p in biased]
    t0 = time.perf_counter()
    guide = coarse_guide(biased, rpcs)
    out = {"seed": seed, "guide_s": time.perf_counter() - t0, "h_range": list(guide.h_range)}
    raw = {}
    for ex in EXTRACTORS:
        t0 = time.perf_counter()
        tracks, _ = tie_point_tracks(biased, rpcs, OrientSpec(extractor=ex), guide=guide, scheduler="synchronous")
        dt = time.perf_counter() - t0
        truth, clear = true_positions(tracks.pos[0], true, info.out_dir)
        raw[ex] = errors(tracks.pos, truth, clear)
        out[ex] = {"tracks": tracks.n, **summarise(*raw[ex]), "seconds": dt,
                   "rejected_p2l": list(tracks.rejected_p2l),
                   "views_per_track": np.bincount(np.isfinite(tracks.pos[..., 0]).sum(axis=0),
                                                  minlength=views + 1)[2:].tolist()}
    return out, raw


def run_views(views: int, tmp: Path) -> dict:
    """Every seed of :data:`SEEDS`, and the pooled figures."""
    per, raw = [], {ex: [] for ex in EXTRACTORS}
    for seed in SEEDS:
        rec, r = run_scene(views, seed, tmp / f"v{views}_s{seed}")
        per.append(rec)
        for ex in EXTRACTORS:
            raw[ex].append(r[ex])
    pooled = {}
    for ex in EXTRACTORS:
        err = np.concatenate([e for e, _ in raw[ex]])
        ok = np.concatenate([o for _, o in raw[ex]])
        pooled[ex] = {"tracks": sum(p[ex]["tracks"] for p in per), **summarise(err, ok),
                      "seconds": sum(p[ex]["seconds"] for p in per)}
    return {"scenes": per, "pooled": pooled}


def run_real(name: str) -> dict:
    from tiledsm.io.cameras import find_camera
    from tiledsm.orient import OrientSpec, orient_images

    if name == "s2p":
        d = SHARED / "s2p_pair" / "input_pair"
        imgs, geoms, tile = [d / "img_01.tif", d / "img_02.tif"], [None, None], 512
    else:
        d = SHARED / "shareloc_phr_ventoux"
        imgs, geoms, tile = [d / "left_image.tif", d / "right_image.tif"], [d / "left_image.geom",
                                                                              d / "right_image.geom"], 256
    rpcs = [find_camera(p, rpc=g)[0] for p, g in zip(imgs, geoms)]
    out = {}
    for ex in EXTRACTORS:
        t0 = time.perf_counter()
        o = orient_images(imgs, spec=OrientSpec(tile=tile, extractor=ex), rpcs=rpcs,
                          scheduler="synchronous")
        out[ex] = {"tracks": o.report["n_tracks"], "rejected_p2l": o.report["tracks"]["rejected_p2l"],
                   "tie_relative_rms_px": o.report["tie_relative_rms_px"], "seconds": time.perf_counter() - t0}
    return out


def run_orientation(views: int, root: Path) -> dict:
    """``benchmarks/orient.py``'s synthetic cases (512 px, seed 4, tiles of 256, 4 GCPs or ties
    only) with each extractor: what the tie points change in the adjusted RPCs."""
    from orient_cases import BIASES, relative_error

    from tiledsm.io.cameras import find_camera
    from tiledsm.orient import OrientSpec, orient_images
    from simulate import biased_copies, corner_points, ground_points, write_points_csv
    from tiledsm.synth import make_scene

    info = make_scene(root / "scene", size=512, views=views, seed=4, chunk=256, workers=1)
    true = [find_camera(p)[0] for p in info.views]
    h = (true[0].height_off - true[0].height_scale, true[0].height_off + true[0].height_scale)
    biased = biased_copies(info.views, true, BIASES[:views], root / "biased", h)
    names, shape = [p.name for p in biased], (512, 512)
    gl, ga, gh = corner_points(true[0], shape, (300, 400), seed=1)
    write_points_csv(root / "gcps.csv", names, true, gl, ga, gh, noise_px=0.05, shape=shape)
    cl, ca, ch = ground_points(true[0], shape, (300, 400), 20, seed=2)
    write_points_csv(root / "checks.csv", names, true, cl, ca, ch, prefix="c", shape=shape)
    lon, lat, hh = ground_points(true[0], shape, (300, 400), 300, seed=3)
    out = {}
    for ex in EXTRACTORS:
        spec = OrientSpec(tile=256, extractor=ex)
        rec = {}
        for case, gcps in (("gcp4", root / "gcps.csv"), ("ties", None)):
            o = orient_images(biased, gcps, root / "checks.csv", spec=spec, scheduler="synchronous")
            rec[case] = {
                "n_tracks": o.report["n_tracks"],
                "vs_true_rpc_px": [float(np.sqrt(np.mean(np.sum((np.stack(a.project(lon, lat, hh), -1)
                                                                  - np.stack(b.project(lon, lat, hh), -1)) ** 2, -1))))
                                   for a, b in zip(o.rpcs_after, true)],
                "relative_truth_px": relative_error(list(o.rpcs_after), true, lon, lat, hh)}
        out[ex] = rec
    return out


def markdown_table(res: dict) -> str:
    """Pooled synthetic rows (3 scenes each), then the real pairs."""
    rows = ["| scenes | extractor | tracks | matches | correct < 1 px | correct < 1 px, clear (n) "
            "| median error px | rel. RMS px | seconds |", "|---|---|---|---|---|---|---|---|---|"]
    for v in (2, 3):
        for ex in EXTRACTORS:
            c = res[f"synthetic_{v}views"]["pooled"][ex]
            rows.append(f"| synthetic, {v} views, seeds {'/'.join(map(str, SEEDS))} | {ex} | {c['tracks']} | "
                        f"{c['matches']} | {c['correct_1px']:.3f} | {c['correct_clear_1px']:.3f} "
                        f"({c['clear_matches']}) | {c['median_error_px']:.3f} | - | {c['seconds']:.1f} |")
    for name in ("s2p", "ventoux"):
        for ex in EXTRACTORS if name in res else ():
            c = res[name][ex]
            rows.append(f"| {name} | {ex} | {c['tracks']} | - | - | - | - | "
                        f"{c['tie_relative_rms_px']['after']:.3f} | {c['seconds']:.1f} |")
    rows += ["", "| orientation (benchmarks/orient.py cases) | extractor | tracks | 4 GCPs: corrected vs true RPCs px "
             "| ties only: relative px (truth) |", "|---|---|---|---|---|"]
    for v in (2, 3):
        for ex in EXTRACTORS:
            c = res[f"orientation_{v}views"][ex]
            vt = ", ".join(f"{x:.3f}" for x in c["gcp4"]["vs_true_rpc_px"])
            rows.append(f"| synthetic 512 px, {v} views | {ex} | {c['gcp4']['n_tracks']} | {vt} | "
                        f"{c['ties']['relative_truth_px']:.3f} |")
    return "\n".join(rows)


def main() -> None:
    import os

    warnings.simplefilter("ignore")
    res = {"command": "nice -n 10 .venv/bin/python benchmarks/tiepoints.py", "load_before": os.getloadavg()}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tiepoints_") as tmp:
        for v in (2, 3):
            res[f"synthetic_{v}views"] = run_views(v, Path(tmp))
        for v in (2, 3):
            res[f"orientation_{v}views"] = run_orientation(v, Path(tmp) / f"orient{v}")
    if SHARED.exists():
        for name in ("s2p", "ventoux"):
            res[name] = run_real(name)
    res["total_s"] = time.perf_counter() - t0
    res["load_after"] = os.getloadavg()
    path = ROOT / "benchmarks" / "results" / "tiepoints.json"
    path.write_text(json.dumps(res, indent=2))
    print(markdown_table(res))
    print(f"\ntotal {res['total_s']:.0f} s; load {res['load_before'][0]:.2f} -> {res['load_after'][0]:.2f}")


if __name__ == "__main__":
    main()
