"""Benchmark ``make_scene``: wall time and peak memory per scene size.

Each size runs in a fresh subprocess (so its peak RSS is its own):
2 views, B/H 0.4, GSD 0.5 m, 512-pixel tiles. Prints a table and writes
``benchmarks/results/synth.json``.

    python benchmarks/synth.py [--sizes 1024 4096 16384] [--workers 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import measure  # noqa: E402

CHILD = r"""
import json, resource, sys, time
from tiledsm.synth import make_scene
size, workers, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
t = time.perf_counter()
info = make_scene(out, size=size, gsd=0.5, bh=0.4, seed=0, views=2, chunk=512, workers=workers)
wall = time.perf_counter() - t
print(json.dumps({"size": size, "wall_s": wall, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "bh_measured": info.bh, "rpc_fit_max_px": max(info.fit_residual_px), "timings_s": info.timings_s}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096])
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", default=None, help="scratch folder for the scenes (default: a temporary one)")
    args = ap.parse_args(argv)
    rows = []
    for size in args.sizes:
        scratch = Path(args.out or tempfile.mkdtemp(prefix="tiledsm_synth_bench_")) / f"scene_{size}"
        log = Path(tempfile.mkstemp(prefix="tiledsm_synth_bench_", suffix=".log")[1])
        # the whole process tree (client + dask workers) is sampled: RUSAGE_SELF alone misses the workers
        m = measure([sys.executable, "-c", CHILD, str(size), str(args.workers), str(scratch)], log=log)
        if not m.ok:
            raise SystemExit(f"make_scene {size} failed (exit {m.returncode}), see {log}")
        row = json.loads(log.read_text().strip().splitlines()[-1])
        row["peak_single_process_mib"] = m.peak_single_rss_mib
        row["peak_tree_pss_mib"] = m.peak_pss_mib
        row["peak_tree_rss_mib"] = m.peak_rss_mib
        row["load"] = [m.load_before, m.load_after]
        row["mpix_per_s"] = 2 * size * size / 1e6 / row["timings_s"]["render_and_write"]
        row["bytes_written"] = sum(p.stat().st_size for p in scratch.glob("*"))
        rows.append(row)
        if args.out is None:
            shutil.rmtree(scratch.parent, ignore_errors=True)
        print(f"{size:>6d} px  {row['wall_s']:8.1f} s  peak RSS client {row['peak_rss_mb']:6.0f} MB, "
              f"largest process {m.peak_single_rss_mib:6.0f} MiB, tree PSS {m.peak_pss_mib or float('nan'):6.0f} MiB  "
              f"render {row['mpix_per_s']:.2f} Mpx/s  B/H {row['bh_measured']:.4f}  "
              f"RPC fit {row['rpc_fit_max_px']:.1e} px", flush=True)
    doc = {"benchmark": "synth.make_scene (2 views, gsd 0.5, bh 0.4, chunk 512)", "workers": args.workers,
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
           "results": rows}
    out = Path(__file__).resolve().parent / "results" / "synth.json"
    if out.exists():  # keep the rows of sizes not measured by this run
        measured = {r["size"] for r in rows}
        kept = [r for r in json.loads(out.read_text()).get("results", []) if r.get("size") not in measured]
        doc["results"] = sorted(kept + rows, key=lambda r: r["size"])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
