"""A DSM through a real SLURM, equal to the local one.

Runs ``tiledsm dsm`` on a synthetic scene twice: on this machine (threads,
the command's default) and with ``--cluster slurm.yaml`` (``kind: slurm``:
dask-jobqueue submits the workers as SLURM batch jobs; the scheduler runs
in the command's process). Needs a SLURM whose jobs run on a machine that
sees the same files, e.g. the one-node SLURM of ``benchmarks/slurm_local.sh``.
Records the jobs SLURM ran (``scontrol show job``: id, state, node, run
time), the wall times, and whether the two DSMs' heights are identical,
cell by cell.

Usage::

    sudo benchmarks/slurm_local.sh start
    .venv/bin/python benchmarks/slurm_run.py [--size 384] [--chunk 128] [--json benchmarks/results/slurm_run.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from same_dsm import heights  # benchmarks/ is the script's folder: on sys.path

ROOT = Path(__file__).resolve().parents[1]


def slurm_jobs() -> dict[str, dict]:
    """SLURM's jobs it still remembers (finished ones for ``MinJobAge``,
    300 s by default), by id."""
    r = subprocess.run(["scontrol", "-o", "show", "job"], capture_output=True, text=True, check=True)
    jobs = {}
    for line in r.stdout.splitlines():
        fields = dict(re.findall(r"(\w+)=(\S*)", line))
        if "JobId" in fields:
            jobs[fields["JobId"]] = {k: fields.get(k) for k in (
                "JobName", "JobState", "NodeList", "NumCPUs", "MinMemoryNode", "RunTime", "SubmitTime", "StartTime",
                "EndTime", "Partition")}
    return jobs


def run(cmd: list[str], env: dict, cwd: Path) -> float:
    """Wall seconds of ``cmd`` run in ``cwd`` (where sbatch leaves the jobs' ``slurm-JOBID.out``)."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    if r.returncode:
        raise SystemExit(f"{' '.join(cmd)}: rc {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=384, help="synthetic scene side, pixels")
    ap.add_argument("--chunk", type=int, default=128, help="DSM chunk side, cells (several chunks: several tasks)")
    ap.add_argument("--cores", type=int, default=2, help="cores (single-threaded workers) per job")
    ap.add_argument("--memory", default="4GiB", help="memory per job")
    ap.add_argument("--max-jobs", type=int, default=1)
    ap.add_argument("--queue", default="debug")
    ap.add_argument("--workdir", default=None, help="folder for the scene and the runs (default: a temporary one)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "slurm_run.json"))
    args = ap.parse_args()

    from tiledsm.synth import make_scene

    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # sbatch exports the environment to the jobs: same code there
    with tempfile.TemporaryDirectory(prefix="slurm_run_", dir=args.workdir) as tmp:
        tmp = Path(tmp)
        scene = make_scene(tmp / "scene", size=args.size, gsd=0.5, bh=0.4, seed=5, views=2)
        cluster = {"kind": "slurm", "jobqueue": {
            "cores": args.cores, "processes": args.cores, "memory": args.memory, "walltime": "00:30:00",
            "queue": args.queue, "minimum_jobs": 1, "maximum_jobs": args.max_jobs}}
        (tmp / "slurm.yaml").write_text(yaml.safe_dump(cluster))
        dsm = [sys.executable, "-m", "tiledsm", "dsm", *map(str, scene.views), "--like", str(scene.truth_dsm),
               "--chunk", str(args.chunk), "--no-progress"]
        commands = {
            "local": dsm + ["--out", str(tmp / "local")],
            "slurm": dsm + ["--out", str(tmp / "slurm"), "--cluster", str(tmp / "slurm.yaml")],
        }
        before = set(slurm_jobs())
        wall = {name: round(run(cmd, env, tmp), 2) for name, cmd in commands.items()}
        jobs = {k: v for k, v in slurm_jobs().items() if k not in before}
        a, b = heights(tmp / "local" / "dsm.zarr"), heights(tmp / "slurm" / "dsm.zarr")
        metrics = json.loads((tmp / "slurm" / "metrics.json").read_text())
    same_nan = bool(np.array_equal(np.isnan(a), np.isnan(b)))
    both = np.isfinite(a) & np.isfinite(b)
    result = {
        "what": "tiledsm dsm of a synthetic pair, locally and on SLURM jobs (--cluster slurm.yaml, dask-jobqueue)",
        "commands": {k: " ".join(["tiledsm", *c[3:]]).replace(str(tmp), "$WORK") for k, c in commands.items()},
        "cluster_yaml": cluster,
        "scene": {"size_px": args.size, "gsd_m": 0.5, "views": 2},
        "grid_cells": int(a.size),
        "slurm": subprocess.run(["sinfo", "-V"], capture_output=True, text=True).stdout.strip(),
        "jobs_submitted": len(jobs),
        "jobs_note": "JobState CANCELLED: dask-jobqueue ends its worker jobs with scancel when the command closes "
                     "its cluster",
        "jobs": jobs,
        "wall_s": wall,
        "chunks": metrics["timings"].get("chunks"),
        "heights_identical": bool(same_nan and np.array_equal(a[both], b[both])),
        "cells_differing": int((a[both] != b[both]).sum()) + int((np.isnan(a) != np.isnan(b)).sum()),
        "finite_fraction": round(float(np.isfinite(b).mean()), 4),
        "machine": f"{platform.node()}: {os.cpu_count()} cores",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0 if result["heights_identical"] and result["jobs_submitted"] > 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
