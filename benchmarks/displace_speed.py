"""Speed and accuracy of the displacement field at 4096², against peers on
the same windows in the same run.

A band-limited noise texture (Gaussian-filtered white noise, 4096² px at
0.5 m) and its copy moved by a known constant shift (Fourier shift
theorem: exact at any fraction) plus sensor noise on both; two cases:

- ``subpixel``: (dy, dx) = (2.37, -1.61) px, within every method's reach;
- ``large``: (dy, dx) = (-17.3, 21.6) px (13.8 m at 0.5 m, a metre-scale
  surface rupture): tiledsm with the pyramid (``levels`` for a maximum
  displacement of the shift's length plus 4 px; one level would be NaN
  beyond its 8 px search).

Methods, each timed on its own (wall clock, this process):

- **tiledsm**: :func:`tiledsm.displace.correlate_orthos` (window 32, step
  8: 512 x 512 = 262 144 cells), dask threads, all cores;
- **scikit-image** ``phase_cross_correlation`` (``upsample_factor=100``,
  ``normalization=None``: its default phase normalisation fails on small
  untapered windows), one 32-px window at a time, on a random subset of
  the same cells (``--peer-cells``; cells/s from that subset);
- **OpenCV DIS optical flow** (``DISOpticalFlow_create`` preset MEDIUM, on
  8-bit images scaled from the 1st-99th percentiles), one dense flow of
  the whole image; its value at each cell is the mean flow of the cell's
  32-px window (what a correlation of that window measures).

Accuracy per method: the RMSE and the share of cells within 0.5 px of the
truth (valid cells), and the valid share. Cells per second: the field's
cells divided by the wall time.

Usage::

    nice -n 10 .venv/bin/python benchmarks/displace_speed.py [--size 4096] [--peer-cells 3000]
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
sys.path.insert(0, str(REPO))

CASES = {"subpixel": (2.37, -1.61), "large": (-17.3, 21.6)}
WINDOW, STEP, RES = 32, 8, 0.5


def texture(n: int, seed: int = 0) -> np.ndarray:
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    return (ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5) * 200 + 1000).astype(np.float32)


def fourier_shift(img: np.ndarray, dy: float, dx: float) -> np.ndarray:
    ky = np.fft.fftfreq(img.shape[0])[:, None]
    kx = np.fft.rfftfreq(img.shape[1])[None, :]
    f = np.fft.rfft2(img.astype(np.float64)) * np.exp(-2j * np.pi * (ky * dy + kx * dx))
    return np.fft.irfft2(f, s=img.shape).astype(np.float32)


def _ortho(a: np.ndarray):
    import rioxarray  # noqa: F401
    import xarray as xr
    from affine import Affine

    ny, nx = a.shape
    d = xr.DataArray(a, dims=("y", "x"), coords={"y": 4e6 - (np.arange(ny) + 0.5) * RES,
                                                   "x": 5e5 + (np.arange(nx) + 0.5) * RES})
    return d.rio.write_crs("EPSG:32631").rio.write_transform(Affine(RES, 0, 5e5, 0, -RES, 4e6))


def _accuracy(dy: np.ndarray, dx: np.ndarray, truth: tuple[float, float], inner: np.ndarray) -> dict:
    ey, ex = dy[inner] - truth[0], dx[inner] - truth[1]
    ok = np.isfinite(ey) & np.isfinite(ex)
    e = np.hypot(ey[ok], ex[ok])
    return {"valid_share": float(ok.mean()),
            "rmse_px": [float(np.sqrt(np.mean(ey[ok] ** 2))), float(np.sqrt(np.mean(ex[ok] ** 2)))] if ok.any() else None,
            "within_0.5px": float(np.mean(e <= 0.5)) if ok.any() else None}


def run_tiledsm(pre, post, truth, inner, levels_for: float | None) -> dict:
    import dask

    from tiledsm.displace import CorrelationParams, correlate_orthos

    levels = 0 if levels_for is None else int(np.ceil(np.log2(levels_for / 8)))
    params = CorrelationParams(window=WINDOW, step=STEP, levels=max(levels, 0))
    f = correlate_orthos(_ortho(pre), _ortho(post), params, chunk=1024)
    t0 = time.perf_counter()
    with dask.config.set(scheduler="threads"):
        dE, dN = dask.compute(f.dE.data, f.dN.data)
    wall = time.perf_counter() - t0
    dy, dx = -np.asarray(dN) / RES, np.asarray(dE) / RES
    return {"method": "tiledsm correlate_orthos" + (f" (levels {params.levels})" if params.levels else ""),
            "cells": int(dy.size), "wall_s": wall, "cells_per_s": dy.size / wall, **_accuracy(dy, dx, truth, inner)}


def run_skimage(pre, post, truth, rows, cols) -> dict:
    from skimage.registration import phase_cross_correlation

    h = WINDOW // 2
    est = np.empty((2, rows.size))
    t0 = time.perf_counter()
    for k in range(rows.size):
        r, c = rows[k], cols[k]
        s, _, _ = phase_cross_correlation(pre[r - h:r + h, c - h:c + h], post[r - h:r + h, c - h:c + h],
                                          upsample_factor=100, normalization=None)
        est[:, k] = -s  # skimage: the shift registering the moving image onto the reference
    wall = time.perf_counter() - t0
    return {"method": "skimage phase_cross_correlation (upsample 100)", "cells": int(rows.size), "wall_s": wall,
            "cells_per_s": rows.size / wall, **_accuracy(est[0], est[1], truth, np.ones(rows.size, bool))}


def run_dis(pre, post, truth, inner) -> dict:
    import cv2
    from scipy import ndimage

    lo, hi = np.percentile(pre, [1, 99])

    def u8(a):
        return np.clip((a - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)

    t0 = time.perf_counter()
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(u8(pre), u8(post), None)  # (h, w, 2): dx, dy of each pre pixel into post
    # the mean flow of each cell's window, sampled at the cell centres
    mean = [ndimage.uniform_filter(flow[..., i], WINDOW) for i in (1, 0)]
    centres = (np.arange(pre.shape[0] // STEP) + 0.5) * STEP
    idx = centres.astype(int)
    dy, dx = (m[np.ix_(idx, idx)] for m in mean)
    wall = time.perf_counter() - t0
    return {"method": "OpenCV DIS optical flow (MEDIUM), window mean", "cells": int(dy.size), "wall_s": wall,
            "cells_per_s": dy.size / wall, **_accuracy(dy, dx, truth, inner)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--peer-cells", type=int, default=3000, help="cells scikit-image measures (a random subset)")
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "displace_speed.json"))
    args = ap.parse_args(argv)
    n = args.size
    base = texture(n)
    rng = np.random.default_rng(1)
    cells = n // STEP
    # cells far enough from the image edges for every method's windows and the largest shift
    margin = int(np.ceil((WINDOW / 2 + 32) / STEP))
    inner = np.zeros((cells, cells), bool)
    inner[margin:-margin, margin:-margin] = True
    pick = rng.choice(np.flatnonzero(inner.ravel()), size=min(args.peer_cells, int(inner.sum())), replace=False)
    pr, pc = np.unravel_index(pick, inner.shape)
    rows, cols = ((pr + 0.5) * STEP).astype(int), ((pc + 0.5) * STEP).astype(int)
    doc = {"benchmark": "displace_speed", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "host": {"cpus": os.cpu_count()}, "size_px": n, "window": WINDOW, "step": STEP,
           "field_cells": cells * cells, "peer_cells": int(pick.size), "cases": {}}
    # compile the numba kernels (cached on disk after the first run) outside the timings
    run_tiledsm(base[:256, :256], base[:256, :256], (0.0, 0.0), np.ones((32, 32), bool), None)
    run_tiledsm(base[:512, :512], base[:512, :512], (0.0, 0.0), np.ones((64, 64), bool), 20.0)
    for case in args.cases:
        truth = CASES[case]
        pre = base + rng.normal(size=base.shape).astype(np.float32) * 2
        post = fourier_shift(base, *truth) + rng.normal(size=base.shape).astype(np.float32) * 2
        if case == "large":
            # one level: NaN beyond its 8 px search (tests/displace/test_cli_displace.py shows it); the pyramid only
            rows_ = [run_tiledsm(pre, post, truth, inner, float(np.hypot(*truth)) + 4)]
        else:
            rows_ = [run_tiledsm(pre, post, truth, inner, None)]
        rows_.append(run_skimage(pre, post, truth, rows, cols))
        rows_.append(run_dis(pre, post, truth, inner))
        doc["cases"][case] = {"shift_px": list(truth), "rows": rows_}
        print(f"\n{case}: shift (dy, dx) = {truth} px, {n}² px, window {WINDOW}, step {STEP}")
        print("| method | cells | wall (s) | cells/s | valid | RMSE dy, dx (px) | within 0.5 px |\n|---|---|---|---|---|---|---|")
        for r in rows_:
            rm = "-" if r["rmse_px"] is None else f"{r['rmse_px'][0]:.4f}, {r['rmse_px'][1]:.4f}"
            w5 = "-" if r["within_0.5px"] is None else f"{r['within_0.5px']:.3f}"
            print(f"| {r['method']} | {r['cells']} | {r['wall_s']:.2f} | {r['cells_per_s']:.0f} | "
                  f"{r['valid_share']:.3f} | {rm} | {w5} |")
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
