"""What fills a DSM worker: data held for other tasks (dask's managed memory)
vs the running task's own arrays, sampled every second.

``tiledsm dsm`` runs on a local cluster this script starts (2 workers, 1
thread each, ``--scheduler``), on synthetic scenes made by ``tiledsm synth``
(e.g. by ``benchmarks/dsm.py``), on their truth grid, chunks of 512; each
second every worker reports its RSS, the bytes of results it holds
(``managed``: outputs waiting for the tasks that need them) and their count.
At the worker's RSS peak, ``managed`` says how much of it is data held for
neighbours (the frontier of the graph's overlap stages) rather than the
running task's arrays.

Usage::

    nice -n 5 .venv/bin/python benchmarks/dsm_worker_memory.py runs/bench_dsm/scene4096 /tmp/bench8k/scene8192

Writes ``benchmarks/results/dsm_worker_memory.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _probe(dask_worker):
    import psutil

    data = dask_worker.data
    managed = getattr(getattr(data, "fast", None), "total_weight", None)
    if managed is None:
        managed = sum(getattr(v, "nbytes", 0) for v in data.values())
    return managed, psutil.Process().memory_info().rss, len(data)


def run(scene: Path, workers: int) -> dict:
    import rasterio
    from dask.distributed import Client, LocalCluster

    with rasterio.open(scene / "truth_dsm.tif") as ds:
        size = ds.width
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True) as cl, Client(cl) as c:
        samples, stop = [], threading.Event()

        def sampler():
            while not stop.is_set():
                try:
                    samples.append(c.run(_probe))
                except Exception:  # a worker busy past the timeout: skip the sample
                    pass
                stop.wait(1.0)

        th = threading.Thread(target=sampler, daemon=True)
        th.start()
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [str(REPO / ".venv" / "bin" / "tiledsm"), "dsm", str(scene / "view_0.tif"), str(scene / "view_1.tif"),
                   "--like", str(scene / "truth_dsm.tif"), "--out", f"{tmp}/dsm", "--scheduler", cl.scheduler_address,
                   "--chunk", "512", "--no-progress"]
            r = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        stop.set()
        th.join()
    if r.returncode:
        return {"size": size, "error": r.stderr[-2000:]}
    per_worker = {}
    for info in samples:
        for w, (managed, rss, n) in info.items():
            p = per_worker.setdefault(w, {"peak_rss_mib": 0.0})
            if rss / 2**20 > p["peak_rss_mib"]:
                p.update(peak_rss_mib=rss / 2**20, managed_at_peak_mib=managed / 2**20, keys_at_peak=n)
            p["max_managed_mib"] = max(p.get("max_managed_mib", 0.0), managed / 2**20)
    return {"size": size, "scene": str(scene), "wall_s": wall, "samples": len(samples), "workers": list(per_worker.values())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path, help="folders made by tiledsm synth")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "dsm_worker_memory.json"))
    args = ap.parse_args(argv)
    rows = [run(s, args.workers) for s in args.scenes]
    print("| grid | wall (s) | worker | peak RSS (MiB) | held for other tasks at that peak (MiB) | results held | most held (MiB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['size']}² | failed | | | | | |")
            continue
        for i, w in enumerate(r["workers"]):
            print(f"| {r['size']}² | {r['wall_s']:.0f} | {i} | {w['peak_rss_mib']:.0f} | {w['managed_at_peak_mib']:.0f} | "
                  f"{w['keys_at_peak']} | {w['max_managed_mib']:.0f} |")
    doc = {"benchmark": "dsm_worker_memory", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "command": " ".join(["benchmarks/dsm_worker_memory.py", *map(str, args.scenes)]), "rows": rows}
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
