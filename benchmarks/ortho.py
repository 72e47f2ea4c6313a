"""Orthoimages of the real Pléiades pair on tiledsm's own DSM: do they agree?

Steps (each as a user runs it, ``tiledsm ...`` in a subprocess):

1. ``tiledsm dsm`` of ``../shared/data/s2p_pair`` on s2p's grid (0.5 m);
2. ``tiledsm ortho`` of each image on that ``dsm.zarr`` (the images keep
   the RPCs they were matched with), for each kernel asked;
3. the two orthos compared on 128 x 128-cell tiles with at least 85 % of
   cells valid in both: sub-pixel shift by phase correlation
   (scikit-image ``phase_cross_correlation``, upsampling 100), reported as
   median / 95th percentile / max over the tiles, in ortho cells; and the
   same with the raw RPCs (``--dsm`` a GeoTIFF copy, so no relative
   correction), to show what the correction is worth.

Usage::

    nice -n 10 .venv/bin/python benchmarks/ortho.py [--kernels cs bl]

Writes ``benchmarks/results/ortho.json`` and prints a markdown table.
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
import rasterio

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO))
from benchmarks._measure import run_tiledsm as _run  # noqa: E402


def tile_shifts(a: np.ndarray, b: np.ndarray, tile: int = 128, min_valid: float = 0.85) -> np.ndarray:
    """Shift magnitudes (cells) between ``a`` and ``b`` on tiles valid in both."""
    from skimage.registration import phase_cross_correlation

    out = []
    for i in range(0, a.shape[0] - tile + 1, tile):
        for j in range(0, a.shape[1] - tile + 1, tile):
            ta, tb = a[i:i + tile, j:j + tile], b[i:i + tile, j:j + tile]
            ok = np.isfinite(ta) & np.isfinite(tb)
            if ok.mean() < min_valid:
                continue
            s, _, _ = phase_cross_correlation(np.where(ok, ta, np.nanmean(ta)), np.where(ok, tb, np.nanmean(tb)),
                                              upsample_factor=100)
            out.append(float(np.hypot(*s)))
    return np.asarray(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kernels", nargs="+", default=["cs", "bl"])
    ap.add_argument("--run-dir", default=str(REPO / "runs" / "bench_ortho"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "ortho.json"))
    args = ap.parse_args(argv)
    pair = DATA / "s2p_pair"
    if not pair.exists():
        raise SystemExit(f"{pair}: shared data not found")
    run = Path(args.run_dir)
    run.mkdir(parents=True, exist_ok=True)
    imgs = [str(pair / "input_pair" / n) for n in ("img_01.tif", "img_02.tif")]
    ref = str(pair / "expected_output" / "pair" / "dsm.tif")
    t_dsm = _run("dsm", *imgs, "--like", ref, "--out", str(run / "dsm"), "--workers", "2", "--overwrite")
    rows = []
    for dsm_name, dsm in (("matched RPCs (dsm.zarr)", run / "dsm" / "dsm.zarr"), ("raw RPCs (dsm.tif)", run / "dsm" / "dsm.tif")):
        for kernel in args.kernels:
            orthos, secs = [], 0.0
            for k, img in enumerate(imgs):
                out = run / f"ortho_{kernel}_{'zarr' if dsm.suffix == '.zarr' else 'tif'}_{k}"
                secs += _run("ortho", img, "--dsm", str(dsm), "--out", str(out), "--kernel", kernel, "--workers", "2")
                with rasterio.open(out / "ortho.tif") as src:
                    orthos.append(src.read(1, masked=True).filled(np.nan).astype(np.float64))
            shifts = tile_shifts(*orthos)
            rows.append({
                "cameras": dsm_name, "kernel": kernel, "tiles": int(shifts.size),
                "median_px": float(np.median(shifts)), "p95_px": float(np.percentile(shifts, 95)),
                "max_px": float(shifts.max()), "valid_a": float(np.isfinite(orthos[0]).mean()),
                "valid_b": float(np.isfinite(orthos[1]).mean()), "ortho_s_both": secs,
            })
            print(rows[-1], flush=True)
    head = "| cameras | kernel | tiles | median shift (px) | 95th pct (px) | max (px) | valid (img 1 / 2) | both orthos (s) |"
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['cameras']} | {r['kernel']} | {r['tiles']} | {r['median_px']:.3f} | {r['p95_px']:.3f} | "
                     f"{r['max_px']:.3f} | {r['valid_a']:.2f} / {r['valid_b']:.2f} | {r['ortho_s_both']:.1f} |")
    table = "\n".join(lines)
    print(table)
    result = {"benchmark": "ortho", "when": _dt.datetime.now().isoformat(timespec="seconds"),
              "command": "benchmarks/ortho.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "dsm_s": t_dsm, "load_avg": os.getloadavg(), "rows": rows, "table": table}
    Path(args.json).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
