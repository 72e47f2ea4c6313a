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
import os
import re
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


PLANNED = re.compile(r"\((\d+) MiB\) per worker")


def _tiledsm(src: Path | None) -> tuple[list[str], dict]:
    """The command that runs tiledsm (this checkout, or the package in
    ``src``, e.g. an export of an earlier commit) and its environment."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    return [str(REPO / ".venv" / "bin" / "python"), "-m", "tiledsm"], env


def _run_elsewhere(scene: Path, workers: int, src: Path) -> dict:
    """:func:`run` in a child process whose ``tiledsm`` is the one in
    ``src`` (the local cluster's workers inherit its path)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": str(src)}
        subprocess.run([sys.executable, __file__, str(scene), "--workers", str(workers), "--json", f"{tmp}/row.json",
                        "--code-label", str(src)], env=env, check=True)
        row = json.loads(Path(f"{tmp}/row.json").read_text())["rows"][0]
    if "error" in row:
        print(f"{scene} with {src} failed:\n{row['error']}", file=sys.stderr)
    return row


def run(scene: Path, workers: int, src: Path | None = None) -> dict:
    import rasterio
    import zarr
    from dask.distributed import Client, LocalCluster

    with rasterio.open(scene / "truth_dsm.tif") as ds:
        size = ds.width
    exe, env = _tiledsm(src)
    args = ["dsm", str(scene / "view_0.tif"), str(scene / "view_1.tif"), "--like", str(scene / "truth_dsm.tif"),
            "--chunk", "512", "--no-progress"]
    with tempfile.TemporaryDirectory() as tmp:
        dry = subprocess.run([*exe, *args, "--out", f"{tmp}/dsm", "--workers", str(workers), "--dry-run"],
                             capture_output=True, text=True, env=env, cwd=tmp)
    found = PLANNED.search(dry.stdout)
    planned = float(found.group(1)) if found else None
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
        levels = None
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [*exe, *args, "--out", f"{tmp}/dsm", "--scheduler", cl.scheduler_address]
            # cwd: not the checkout, whose tiledsm/ would shadow PYTHONPATH's under ``python -m``
            r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp)
            if r.returncode == 0:
                levels = zarr.open_group(f"{tmp}/dsm/dsm.zarr", mode="r").attrs.get("levels")
        wall = time.perf_counter() - t0
        stop.set()
        th.join()
    if r.returncode:
        return {"size": size, "code": str(src) if src else "checkout", "error": r.stderr[-2000:]}
    per_worker = {}
    for info in samples:
        for w, (managed, rss, n) in info.items():
            p = per_worker.setdefault(w, {"peak_rss_mib": 0.0})
            if rss / 2**20 > p["peak_rss_mib"]:
                p.update(peak_rss_mib=rss / 2**20, managed_at_peak_mib=managed / 2**20, keys_at_peak=n)
            p["max_managed_mib"] = max(p.get("max_managed_mib", 0.0), managed / 2**20)
    return {"size": size, "scene": str(scene), "code": str(src) if src else "checkout", "levels": levels,
            "planned_worker_mib": planned, "wall_s": wall, "samples": len(samples),
            "workers": list(per_worker.values())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path, help="folders made by tiledsm synth")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--src", type=Path, help="also run the package in this folder (an export of another commit), "
                    "client and workers alike, before each scene")
    ap.add_argument("--code-label", type=Path, help=argparse.SUPPRESS)  # set by --src for its own child run
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "dsm_worker_memory.json"))
    args = ap.parse_args(argv)
    rows = []
    for s in [p.resolve() for p in args.scenes]:
        if args.src is not None:
            rows.append(_run_elsewhere(s, args.workers, args.src))
        rows.append(run(s, args.workers, args.code_label))
    print("| grid | code | levels | wall (s) | planned per worker (MiB) | worker | peak RSS (MiB) | peak / planned "
          "| held for other tasks at that peak (MiB) | results held | most held (MiB) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['size']}² | {r.get('code', '')} | failed | | | | | | | | |")
            continue
        planned = r.get("planned_worker_mib")
        for i, w in enumerate(r["workers"]):
            ratio = f"{w['peak_rss_mib'] / planned:.2f}" if planned else "-"
            print(f"| {r['size']}² | {r['code']} | {r['levels']} | {r['wall_s']:.0f} | {planned or '-'} | {i} "
                  f"| {w['peak_rss_mib']:.0f} | {ratio} | {w['managed_at_peak_mib']:.0f} | {w['keys_at_peak']} "
                  f"| {w['max_managed_mib']:.0f} |")
    doc = {"benchmark": "dsm_worker_memory", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "command": " ".join(["benchmarks/dsm_worker_memory.py", *map(str, argv if argv is not None else sys.argv[1:])]),
           "rows": rows}
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
