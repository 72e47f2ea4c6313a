"""Horizontal displacement by ortho correlation: accuracy, noise floor, speed.

Three measurements, each printed as a table and written to
``benchmarks/results/displacement.json``:

1. **Synthetic event** (``recipes/deformation.yaml``, run as a user runs it:
   ``tiledsm run``, then ``tiledsm evaluate`` on its folder, untimed):
   per-component errors of dE/dN/dU against the known truth, the offsets
   across the fault (slip, opening, throw) with their stated errors, the
   share of cells within +-2 sigma.
2. **Real noise floor**: the two images of ``../shared/data/s2p_pair``
   orthorectified on tiledsm's DSM of that pair (``tiledsm dsm`` then
   ``tiledsm ortho``, as a user runs them), then correlated
   (:func:`tiledsm.displace.correlate_orthos`): nothing moved, so the
   dE/dN median and NMAD over the whole overlap are the noise floor of
   real data.
3. **Kernel against a peer**: on windows of a Fourier-shifted noise texture
   (known sub-pixel shifts), bias, NMAD and time per window of
   :func:`tiledsm.displace.correlate_windows` against scikit-image's
   ``phase_cross_correlation`` (upsampling 100, ``normalization=None``: its
   default pure-phase normalisation fails on these small untapered windows),
   one window at a time.

Usage::

    nice -n 10 .venv/bin/python benchmarks/displacement.py [--skip-real] [--skip-synthetic]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO))
from benchmarks._measure import run_tiledsm as _run  # noqa: E402


def _stats(v: np.ndarray) -> dict:
    v = v[np.isfinite(v)]
    med = float(np.median(v))
    return {"count": int(v.size), "mean": float(v.mean()), "median": med,
            "nmad": float(1.4826 * np.median(np.abs(v - med))), "le95": float(np.percentile(np.abs(v), 95))}


def synthetic(work: Path) -> dict:
    out = work / "deformation"
    wall = _run("run", str(REPO / "recipes" / "deformation.yaml"), "--out", str(out), "--overwrite")
    m = json.loads((out / "metrics.json").read_text())
    d = m["displacement"]
    # the errors against the truth: tiledsm evaluate on the finished folder (outside the timed run)
    from tiledsm.evaluate import evaluate_run

    t = evaluate_run(out)["scores"]["displacement"]
    res = d["grid"]["resolution_m"] / d["grid"]["step_px"]
    rows = []
    for c in ("dE", "dN", "dU"):
        s = t["components"][c]
        rows.append({"component": c, "rmse_m": s["all"]["rmse"], "mean_m": s["all"]["mean"], "nmad_m": s["all"]["nmad"],
                     "nmad_px": s["all"]["nmad"] / res, "stable_nmad_px": d["stable_noise"][c]["nmad_px"],
                     "within_2_sigma": s["within_2_sigma"]})
    offsets = {k: v for k, v in t.get("offsets", {}).items() if k != "nominal"}
    return {"command": f"tiledsm run recipes/deformation.yaml --out {out}; tiledsm evaluate {out}", "wall_s": wall,
            "components": rows,
            "offsets": offsets, "uplift": t.get("uplift"), "timings": d["timings"],
            "nominal": t.get("offsets", {}).get("nominal")}


def real(work: Path) -> dict:
    from tiledsm.displace import CorrelationParams, correlate_orthos
    from tiledsm.io import open_product

    pair = DATA / "s2p_pair"
    if not pair.exists():
        raise SystemExit(f"{pair} is missing: the real-data noise floor needs ../shared/data/s2p_pair")
    ref = pair / "expected_output" / "pair" / "dsm.tif"
    imgs = [pair / "input_pair" / "img_01.tif", pair / "input_pair" / "img_02.tif"]
    dsm = work / "s2p_dsm"
    t_dsm = _run("dsm", *map(str, imgs), "--like", str(ref), "--out", str(dsm), "--overwrite")
    t_ortho = 0.0
    for i, img in enumerate(imgs):
        t_ortho += _run("ortho", str(img), "--dsm", str(dsm / "dsm.zarr"), "--kernel", "cs", "--out",
                        str(work / f"ortho_{i}"))
    a = open_product(work / "ortho_0" / "ortho.zarr")
    b = open_product(work / "ortho_1" / "ortho.zarr")
    params = CorrelationParams()
    t0 = time.perf_counter()
    f = correlate_orthos(a, b, params).compute()
    t_corr = time.perf_counter() - t0
    res = abs(float(a.rio.transform().a))
    dE, dN = f["dE"].values, f["dN"].values
    both = np.isfinite(a.values) & np.isfinite(b.values)
    return {
        "commands": [f"tiledsm dsm img_01.tif img_02.tif --like {ref.name} --out {dsm}",
                     "tiledsm ortho img_0{1,2}.tif --dsm dsm.zarr --kernel cs", "correlate_orthos(window 32, step 8)"],
        "ortho_shape": list(a.shape), "resolution_m": res, "overlap_share": float(both.mean()),
        "cells": int(dE.size), "valid_share": float(np.isfinite(dE).mean()),
        "dE_m": _stats(dE), "dN_m": _stats(dN),
        "dE_px": _stats(dE / res), "dN_px": _stats(dN / res),
        "timings_s": {"dsm": t_dsm, "orthos": t_ortho, "correlation": t_corr},
    }


def kernel_vs_peer(n_windows: int = 400) -> dict:
    from scipy import ndimage
    from skimage.registration import phase_cross_correlation

    from tiledsm.displace import CorrelationParams, correlate_windows

    rng = np.random.default_rng(1)
    n = 512
    base = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5) * 200 + 100
    ky, kx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
    params = CorrelationParams()
    rows = []
    for dy, dx in ((0.3, -0.7), (2.45, -3.1)):
        post = np.real(np.fft.ifft2(np.fft.fft2(base) * np.exp(-2j * np.pi * (ky * dy + kx * dx))))
        pre_n = base + rng.normal(size=base.shape) * 2
        post_n = post + rng.normal(size=base.shape) * 2
        r = rng.integers(64, n - 64, n_windows)
        c = rng.integers(64, n - 64, n_windows)
        t0 = time.perf_counter()
        ours = correlate_windows(pre_n, post_n, r, c, params)
        t_ours = (time.perf_counter() - t0) / n_windows
        h = params.window // 2
        peer = np.empty((2, n_windows))
        t0 = time.perf_counter()
        for k in range(n_windows):
            wa = pre_n[r[k] - h:r[k] + h, c[k] - h:c[k] + h]
            wb = post_n[r[k] - h:r[k] + h, c[k] - h:c[k] + h]
            # normalization=None (plain cross-correlation): the default "phase" fails on small untapered windows
            s, _, _ = phase_cross_correlation(wa, wb, upsample_factor=100, normalization=None)
            peer[:, k] = -s  # skimage: the shift that registers the moving image onto the reference
        t_peer = (time.perf_counter() - t0) / n_windows
        for name, est, tt in (("tiledsm", ours[:2], t_ours), ("skimage phase_cross_correlation", peer, t_peer)):
            ey, ex = est[0] - dy, est[1] - dx
            rows.append({"method": name, "shift_px": [dy, dx], "bias_px": [float(np.nanmean(ey)), float(np.nanmean(ex))],
                         "nmad_px": [_stats(ey)["nmad"], _stats(ex)["nmad"]], "ms_per_window": 1e3 * tt,
                         "window": params.window})
    return {"windows": n_windows, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/tiledsm_bench_displacement")
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "displacement.json"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": "displacement", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "host": {"cpus": os.cpu_count()}}
    doc["kernel_vs_peer"] = kernel_vs_peer()
    print("| method | shift (px) | bias (px) | NMAD (px) | ms / window |\n|---|---|---|---|---|")
    for r in doc["kernel_vs_peer"]["rows"]:
        print(f"| {r['method']} | {r['shift_px']} | {r['bias_px'][0]:+.4f}, {r['bias_px'][1]:+.4f} | "
              f"{r['nmad_px'][0]:.4f}, {r['nmad_px'][1]:.4f} | {r['ms_per_window']:.2f} |")
    if not args.skip_synthetic:
        doc["synthetic"] = s = synthetic(work)
        print(f"\nsynthetic event ({s['command']}, {s['wall_s']:.0f} s)")
        print("| component | RMSE (m) | mean (m) | NMAD (m) | NMAD (px) | stable NMAD (px) | within ±2σ |")
        print("|---|---|---|---|---|---|---|")
        for r in s["components"]:
            print(f"| {r['component']} | {r['rmse_m']:.4f} | {r['mean_m']:+.4f} | {r['nmad_m']:.4f} | {r['nmad_px']:.4f} | "
                  f"{r['stable_nmad_px']:.4f} | {r['within_2_sigma']:.3f} |")
        print("| offset | measured (m) | truth (m) | error (m) | stated error (m) |\n|---|---|---|---|---|")
        for k, v in s["offsets"].items():
            print(f"| {k} | {v['measured']:+.4f} | {v['truth']:+.4f} | {v['error']:+.4f} | {v['stated_error']:.4f} |")
    if not args.skip_real:
        doc["real"] = r = real(work)
        print(f"\nreal pair, no motion (s2p, {r['ortho_shape']} px at {r['resolution_m']} m, "
              f"{r['valid_share']:.1%} of {r['cells']} cells valid)")
        print("| component | median (px) | mean (px) | NMAD (px) | NMAD (m) |\n|---|---|---|---|---|")
        for c in ("dE", "dN"):
            p, m = r[f"{c}_px"], r[f"{c}_m"]
            print(f"| {c} | {p['median']:+.4f} | {p['mean']:+.4f} | {p['nmad']:.4f} | {m['nmad']:.4f} |")
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
