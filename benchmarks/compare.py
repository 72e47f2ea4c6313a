"""Benchmark: difference of two large synthetic DSMs with bounded memory.

Both DSMs are generated lazily by dask (an analytic terrain evaluated per
block, never held in memory); the other DSM is the terrain sampled 1.6 rows
and 2.3 columns further, plus 0.75 m. ``compare_dsms`` runs on a
``LocalCluster`` (``--workers`` single-threaded processes, ``--memory-limit``
each) and writes every product (dh.zarr, dh.tif COG, figures, metrics,
report). A thread samples the resident memory (RSS) of the client process
and of every worker process every 0.2 s.

Usage::

    .venv/bin/python benchmarks/compare.py --sizes 8192 16384 --chunks 1024

Results: ``benchmarks/results/compare.json`` and ``compare.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import threading
import time
from pathlib import Path

import dask.array as da
import numpy as np
import psutil
import xarray as xr

RES = 2.0
X0, Y0 = 500_000.0, 4_400_000.0
CRS = "EPSG:32632"
_rng = np.random.default_rng(7)
_LAM = _rng.uniform(200.0, 8000.0, 6)
_TH = _rng.uniform(0, np.pi, 6)
_PH = _rng.uniform(0, 2 * np.pi, 6)
_AMP = 0.03 * _LAM


def _terrain_block(block, drow, dcol, dz, block_info=None):
    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    r = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5 + drow
    c = np.arange(c0, c1, dtype=np.float64)[None, :] + 0.5 + dcol
    x, y = RES * c, -RES * r
    z = 1000.0 + 0.01 * x + dz
    for lam, th, ph, a in zip(_LAM, _TH, _PH, _AMP):
        z = z + a * np.sin(2 * np.pi * (x * np.cos(th) + y * np.sin(th)) / lam + ph)
    return z.astype(np.float32)


def lazy_dsm(n: int, chunks: int, name: str, drow=0.0, dcol=0.0, dz=0.0) -> xr.DataArray:
    """An n x n DSM computed block by block on demand."""
    import rioxarray  # noqa: F401
    from affine import Affine

    # a template of zeros carries only the block structure (never materialised whole)
    data = da.zeros((n, n), chunks=chunks, dtype=np.float32).map_blocks(
        _terrain_block, drow, dcol, dz, dtype=np.float32, meta=np.empty((0, 0), np.float32))
    arr = xr.DataArray(data, dims=("y", "x"),
                       coords={"y": Y0 - RES * (np.arange(n) + 0.5), "x": X0 + RES * (np.arange(n) + 0.5)},
                       attrs={"source": f"synthetic {name} {n}x{n}"})
    return arr.rio.write_crs(CRS).rio.write_transform(Affine(RES, 0, X0, 0, -RES, Y0))


class MemorySampler(threading.Thread):
    """Peak RSS of this process and of each descendant process."""

    def __init__(self, period=0.2):
        super().__init__(daemon=True)
        self.period, self.stop_flag = period, threading.Event()
        self.peak_client = 0
        self.peak_worker = 0
        self.peak_total = 0

    def run(self):
        me = psutil.Process()
        while not self.stop_flag.is_set():
            try:
                own = me.memory_info().rss
                kids = []
                for p in me.children(recursive=True):
                    try:
                        kids.append(p.memory_info().rss)
                    except psutil.Error:
                        pass
                self.peak_client = max(self.peak_client, own)
                self.peak_worker = max([self.peak_worker] + kids)
                self.peak_total = max(self.peak_total, own + sum(kids))
            except psutil.Error:
                pass
            time.sleep(self.period)


def run_one(n: int, chunks: int, workers: int, memory_limit: str, out_root: Path) -> dict:
    from tiledsm.cluster import ClusterConfig, compute_context
    from tiledsm.compare import CompareParams, compare_dsms

    ref = lazy_dsm(n, chunks, "ref")
    other = lazy_dsm(n, chunks, "other", 1.6, 2.3, 0.75)
    out = out_root / f"compare_{n}"
    with compute_context(ClusterConfig(workers=workers, memory_limit=memory_limit, progress=False)):
        sampler = MemorySampler()
        sampler.start()
        t0 = time.perf_counter()
        res = compare_dsms(ref, other, out, CompareParams(chunks=chunks))
        wall = time.perf_counter() - t0
        sampler.stop_flag.set()
        sampler.join()
    c = res.metrics["coregistration"]
    st = res.metrics["statistics"]
    row = {
        "size": n, "cells": n * n, "chunks": chunks, "workers": workers, "memory_limit": memory_limit,
        "wall_s": round(wall, 2), "mcells_per_s": round(n * n / 1e6 / wall, 3),
        "timings_s": {k: round(v, 2) for k, v in res.metrics["timings_s"].items()},
        "peak_rss_worker_mb": round(sampler.peak_worker / 2**20, 1),
        "peak_rss_client_mb": round(sampler.peak_client / 2**20, 1),
        "peak_rss_total_mb": round(sampler.peak_total / 2**20, 1),
        "dh_float32_mb": round(n * n * 4 / 2**20, 1),
        "dx_px": c["dx_px"], "dy_px": c["dy_px"], "dz": c["dz"],
        "stable_nmad_m": st["stable"]["nmad"], "stable_rmse_m": st["stable"]["rmse"],
        "dh_tif_mb": round((out / "dh.tif").stat().st_size / 2**20, 1),
    }
    shutil.rmtree(out, ignore_errors=True)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8192, 16384])
    ap.add_argument("--chunks", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--memory-limit", default="2GiB")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"))
    ap.add_argument("--scratch", default=None, help="where products are written (default: a temp folder)")
    args = ap.parse_args(argv)
    scratch = Path(args.scratch or tempfile.mkdtemp(prefix="tiledsm-bench-compare-"))
    rows = []
    for n in args.sizes:
        row = run_one(n, args.chunks, args.workers, args.memory_limit, scratch)
        print(json.dumps(row))
        rows.append(row)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "note": "synthetic DSMs generated lazily; shift (1.6 rows, 2.3 cols), +0.75 m; all products written"}
    (out / "compare.json").write_text(json.dumps({"meta": meta, "runs": rows}, indent=2))
    lines = ["| size | chunks | workers x limit | wall (s) | Mcells/s | peak RSS/worker (MB) | peak RSS client (MB) | dh size (MB) | dx_px | dy_px | dz (m) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['size']}² | {r['chunks']} | {r['workers']} x {r['memory_limit']} | {r['wall_s']} | {r['mcells_per_s']} | "
                     f"{r['peak_rss_worker_mb']} | {r['peak_rss_client_mb']} | {r['dh_float32_mb']} | {r['dx_px']:.4f} | {r['dy_px']:.4f} | {r['dz']:.4f} |")
    (out / "compare.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
