"""Benchmark the DSM stage: wall time, output Mcells/s, peak memory, 1 vs 2 workers.

Cases (each run as the user runs it, ``tiledsm dsm ...``, in a fresh process tree
measured by :mod:`benchmarks._measure`):

- ``s2p``: the real Pleiades pair ``../shared/data/s2p_pair`` on s2p's own grid
  (``--like expected_output/pair/dsm.tif``: 721 x 739 cells of 0.5 m), scored
  against s2p's DSM (NMAD, completeness; and where the DSM lies relative to it,
  Nuth & Kaab, with the NMAD once moved back: the plain NMAD counts a
  georeferencing offset between the two pipelines as height error on slopes);
- ``synth<N>``: a synthetic N x N px scene (GSD 0.5 m, B/H 0.4, made once by
  ``tiledsm synth`` into the run folder and reused), on its truth grid, scored
  against the truth DSM.

The timed command is what a user runs to make the DSM: views, ``--like``,
workers; tie points, matching, the COG and the quick-look included. The
scores against the reference are computed afterwards from the DSM store,
with the same call ``tiledsm dsm --reference`` makes
(:func:`score_run`; the same numbers), and timed apart (``score_s``):
they are the benchmark's measurement, not the user's work. (Results
written before 2026-11-26 timed the command with ``--reference``, about
4-5 s more on the 4096² scene.)

For every case, scheduler (``--schedulers``: ``threads``, W threads of the
command's own process, the default of ``tiledsm dsm``; ``cluster``, a local
cluster of W worker processes asked for by a ``--cluster`` file) and worker
count: wall time of the whole command, the DSM stage's own matching time
(``timings.match_s`` of ``metrics.json``: cluster start included), output
Mcells per second of wall time and of matching, peak memory of one worker
(the largest descendant process; none on threads), of the client (the
command's own process: tie points, then the completeness, in memory; on
threads it runs the tasks too) and of the whole tree (PSS,
shared pages split), and the speed-up of 2 workers over 1 measured in the
same run; for the synthetic cases of a run, the
per-worker peak against the smallest scene's and the client's growth
against one float32 array of the whole scene (the client must never hold
one: the script fails if it grows by that much). Load averages before and after each measurement are recorded:
on a shared machine other work stretches wall times. Before each run the same
command is planned (``--dry-run``) and the plan's estimated peak memory per
worker is set beside the measured one (issue 18: within 1.5x).

``--bounds XMIN YMIN XMAX YMAX`` runs a synthetic case on that part of its
truth grid only: a worker's peak is that of its largest task (chunk plus
halo, candidate heights of the scene's height range), not of the scene's
size, so a 16384^2 scene's per-worker peak is measured in minutes.

Graph construction (no matching): the lazy DSM of a 4096^2, 8192^2 and
16384^2 ground grid at chunks of 256 with 3 pyramid levels (the views of a
small synthetic scene; nothing is computed): seconds to build the dask
array (``dsm_from_views``), seconds to materialise its task graph (what a
scheduler does first), the task count and tasks per chunk (linear growth =
constant tasks per chunk).

Usage::

    nice -n 10 .venv/bin/python benchmarks/dsm.py [--cases s2p synth4096] [--workers 1 2] [--schedulers threads cluster] [--graph-sizes 4096 8192 16384]
    .venv/bin/python benchmarks/dsm.py --cases synth4096 --workers 16 --devices cpu cuda --graph-sizes --warmup  # on a GPU

``--devices`` runs each case with matching on each device (``tiledsm dsm
--device``; ``cpu`` is the compiled kernel, ``cuda`` the same matching as CUDA kernels).
A case written ``synth16384@cuda`` runs on that device only. Where a case ran
on two devices with the same workers, the two DSMs are compared cell by cell
(``device_agreement``: the share of cells valid in one only, and of cells
valid in both whose heights differ by more than 1e-3 m; issue 20 allows
0.1 % each). ``--score-max-size N`` leaves the scoring against the truth out
for cases larger than N² cells (their rows have no NMAD). ``--warmup``
first runs the 256² scene on each device, untimed (:func:`warm_caches`).

Writes ``benchmarks/results/dsm.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import measure, scheduler_args  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data"))
TILEDSM = Path(sys.executable).parent / "tiledsm"


def _case_s2p(run_dir: Path) -> tuple[list[str], dict]:
    pair = DATA / "s2p_pair"
    if not pair.exists():
        raise SystemExit(f"{pair}: shared data not found (expected ../shared/data beside the repository)")
    ref = pair / "expected_output" / "pair" / "dsm.tif"
    images = [str(pair / "input_pair" / n) for n in ("img_01.tif", "img_02.tif")]
    return images + ["--like", str(ref)], {"data": str(pair), "reference": "s2p DSM", "reference_path": str(ref)}


def _case_synth(run_dir: Path, size: int) -> tuple[list[str], dict]:
    scene = run_dir / f"scene{size}"
    if not (scene / "truth_dsm.tif").exists():
        m = measure([str(TILEDSM), "synth", str(scene), "--size", str(size), "--gsd", "0.5", "--bh", "0.4", "--seed", "0"],
                    log=run_dir / f"synth{size}.log")
        if not m.ok:
            raise SystemExit(f"tiledsm synth failed, see {run_dir / f'synth{size}.log'}")
    images = sorted(str(p) for p in scene.glob("view_*.tif"))
    truth = str(scene / "truth_dsm.tif")
    return images + ["--like", truth], {"data": f"synthetic {size}x{size} px", "reference": "truth", "reference_path": truth}


def case_args(name: str, run_dir: Path) -> tuple[list[str], dict]:
    """``tiledsm dsm`` arguments (views, ``--like``) and the row's facts of
    case ``name``: ``s2p`` or ``synth<N>``; ``reference_path`` is the DSM
    its result is scored against (:func:`score_run`)."""
    return _case_s2p(run_dir) if name == "s2p" else _case_synth(run_dir, int(name.removeprefix("synth")))


def score_run(out: Path, reference: str, workers: int = 2) -> tuple[dict, float]:
    """``(vs_reference, seconds)``: the statistics of ``out/dsm.zarr``
    against ``reference`` as ``tiledsm dsm --reference`` reports them (the
    same call: :func:`tiledsm.compare.accuracy.reference_accuracy`,
    co-registration included, chunk by chunk on ``workers`` threads), and
    the time they took. The timed command leaves them out: scoring against
    a truth is the benchmark's measurement, not the user's DSM."""
    import time

    import dask

    from tiledsm.compare.accuracy import reference_accuracy
    from tiledsm.io import open_product
    from tiledsm.workflows.common import grid_chunk

    t0 = time.perf_counter()
    height = open_product(out / "dsm.zarr")["height"]
    with dask.config.set(scheduler="threads", num_workers=workers):
        stats, _ = reference_accuracy(height, reference, chunks=grid_chunk(height), coregister=True)
    return {"reference": str(reference), **stats}, time.perf_counter() - t0


PLANNED = re.compile(r"\((\d+) MiB\) per worker")


def planned_worker_mib(argv: list[str]) -> float | None:
    """The plan's estimated peak per worker (``--dry-run`` of ``argv``), MiB."""
    r = subprocess.run([*argv, "--dry-run"], capture_output=True, text=True, timeout=600)
    found = PLANNED.search(r.stdout)
    if r.returncode != 0 or not found:
        print(f"dry run failed (rc {r.returncode}):\n{r.stdout[-1500:]}{r.stderr[-1500:]}", file=sys.stderr)
        return None
    return float(found.group(1))


def _device_name(device: str) -> str:
    from numba import cuda

    if not device.startswith("cuda"):
        return device
    with cuda.gpus[int(device.partition(":")[2] or 0)]:
        name = cuda.get_current_device().name
    return name.decode() if isinstance(name, bytes) else name


def warm_caches(run_dir: Path, devices: list[str]) -> None:
    """One untimed two-level ``tiledsm dsm`` of the 256² scene per device:
    numba compiles the kernels of both the coarsest and the coarse-to-fine
    levels once per machine and caches them on disk, and a timed run that
    compiled one would wait on numba's compiler lock (a GPU machine's first
    4096² run: 6 % of its matching tasks' stack samples,
    ``results/dsm_phases_gpu.json``)."""
    args, _ = _case_synth(run_dir, 256)
    for device in devices:
        out = run_dir / f"warm_{device.replace(':', '')}"
        shutil.rmtree(out, ignore_errors=True)
        argv = [str(TILEDSM), "dsm", *args, "--out", str(out), "--levels", "2", "--device", device,
                "--workers", "2", "--scheduler", "threads", "--no-progress"]
        done = subprocess.run(argv, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"warm-up failed: {' '.join(argv)}\n{done.stderr[-2000:]}")


def run_case(name: str, workers: int, run_dir: Path, chunk: int, timeout: float,
             bounds: list[float] | None = None, scheduler: str = "threads", levels: int | None = None,
             device: str = "cpu", score_max_size: int = 0) -> dict:
    args, info = case_args(name, run_dir)
    if bounds:
        if name == "s2p":
            raise SystemExit("--bounds is for synthetic cases (s2p runs on s2p's grid)")
        # the truth grid's CRS and cells, cut to the bounds; still scored against the truth
        import rasterio

        with rasterio.open(args[args.index("--like") + 1]) as src:
            crs, res = src.crs.to_string(), abs(src.res[0])
        i = args.index("--like")
        args = args[:i] + args[i + 2:] + ["--crs", crs, "--resolution", str(res), "--bounds", *map(str, bounds)]
        info = {**info, "bounds": bounds}
    out = run_dir / (f"{name}_w{workers}" if scheduler == "cluster" else f"{name}_w{workers}_{scheduler}")
    if levels:
        args = [*args, "--levels", str(levels)]
        info = {**info, "levels_asked": levels}
        out = out.with_name(f"{out.name}_L{levels}")
    if device != "cpu":
        args = [*args, "--device", device]
        info = {**info, "device": device, "device_name": _device_name(device)}
        out = out.with_name(f"{out.name}_{device.replace(':', '')}")
    shutil.rmtree(out, ignore_errors=True)  # a finished store would be resumed, not recomputed
    how = scheduler_args(scheduler, workers, run_dir)
    argv = [str(TILEDSM), "dsm", *args, "--out", str(out), *how, "--chunk", str(chunk), "--no-progress"]
    planned = planned_worker_mib(argv)
    log = out.with_suffix(".log")
    m = measure(argv, log=log, timeout=timeout)
    row = {"case": name, "scheduler": scheduler, "workers": workers, "chunk": chunk, **info,
           "planned_worker_mib": planned, "measurement": m.to_dict()}
    if m.ok:
        metrics = json.loads((out / "metrics.json").read_text())
        cells = metrics["report"]["grid"]["width"] * metrics["report"]["grid"]["height"]
        row["out"] = str(out)
        if score_max_size and cells > score_max_size ** 2:
            ref = {}
        else:
            ref, row["score_s"] = score_run(out, info["reference_path"], workers)
        row.update(
            cells=cells,
            match_s=metrics["timings"]["match_s"],
            mcells_per_s=cells / 1e6 / metrics["timings"]["match_s"],
            mcells_per_s_wall=cells / 1e6 / m.wall_s,
            nmad_m=ref.get("nmad"),
            # where the DSM lies relative to the reference (Nuth & Kaab) and its NMAD moved back onto it
            nmad_coregistered_m=(ref.get("coregistered") or {}).get("nmad"),
            offset_east_north_m=[(ref.get("coregistered") or {}).get(k) for k in ("offset_east_m", "offset_north_m")],
            completeness=ref.get("completeness"),
            completeness_in_footprint=metrics.get("completeness_in_footprint"),
            # per pyramid level: chunks, cells searched, mean candidate heights per searched cell
            levels=metrics["timings"].get("levels"),
        )
    else:  # the log's end where the run folder does not outlive the run (a lent GPU machine)
        tail = log.read_text(errors="replace").splitlines()[-15:] if log.exists() else []
        print(f"{name} on {device}, {workers} {scheduler} workers failed (rc {m.returncode}); end of {log}:",
              *tail, sep="\n", file=sys.stderr)
    return row


def device_agreement(rows: list[dict]) -> list[dict]:
    """For each case and worker count that ran on ``cpu`` and on another
    device: the share of the grid's cells valid in one DSM only, and of
    cells valid in both whose heights differ by more than 1e-3 m (issue
    20's terms, at most 0.1 % each), read chunk by chunk."""
    import numpy as np
    import zarr

    out = []
    done = {(r["case"], r["workers"], r.get("device", "cpu")): r for r in rows if "match_s" in r}
    for (case, workers, device), r in done.items():
        cpu = done.get((case, workers, "cpu"))
        if device == "cpu" or cpu is None:
            continue
        a = zarr.open_group(str(Path(cpu["out"]) / "dsm.zarr"), mode="r")["height"]
        b = zarr.open_group(str(Path(r["out"]) / "dsm.zarr"), mode="r")["height"]
        step = 1024
        one = both = off = 0
        for i in range(0, a.shape[0], step):
            x, y = a[i:i + step], b[i:i + step]
            fa, fb = np.isfinite(x), np.isfinite(y)
            one += int(np.count_nonzero(fa != fb))
            both += int(np.count_nonzero(fa & fb))
            off += int(np.count_nonzero(np.abs(x - y)[fa & fb] > 1e-3))
        out.append({"case": case, "workers": workers, "devices": ["cpu", device], "cells": int(a.size),
                    "valid_in_one_share": one / a.size, "valid_in_both": both,
                    "off_1mm_share": off / both if both else 0.0})
    return out


def graph_rows(run_dir: Path, sizes: list[int], chunk: int = 256, levels: int = 3) -> list[dict]:
    """Build (not compute) the DSM graph of ``size``^2 grids; see the module docstring."""
    import time

    import rioxarray

    from tiledsm.dsm import DSMParams, dsm_from_views, open_views
    from tiledsm.geometry.grid import GroundGrid

    args, _ = _case_synth(run_dir, 256)
    views = open_views(args[:2])
    truth = rioxarray.open_rasterio(args[3])
    x0, _, _, y0 = truth.rio.bounds()
    rows = []
    for n in sizes:
        grid = GroundGrid(crs=truth.rio.crs.to_string(), x0=x0, y0=y0, resolution=abs(truth.rio.resolution()[0]),
                          width=n, height=n, chunk=chunk)
        t0 = time.perf_counter()
        arr = dsm_from_views(views, grid, (300.0, 400.0), DSMParams(chunk=chunk, levels=levels))["height"].data
        t1 = time.perf_counter()
        tasks = len(dict(arr.__dask_graph__()))
        t2 = time.perf_counter()
        chunks = len(arr.chunks[0]) * len(arr.chunks[1])
        rows.append({"size": n, "chunk": chunk, "levels": levels, "chunks": chunks, "tasks": tasks,
                     "tasks_per_chunk": tasks / chunks, "build_s": t1 - t0, "materialise_s": t2 - t1})
    return rows


def format_graph_table(rows: list[dict]) -> str:
    head = "| grid | chunks | tasks | tasks per chunk | build (s) | materialise (s) |"
    lines = [head, "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['size']}² | {r['chunks']} | {r['tasks']} | {r['tasks_per_chunk']:.1f} | "
                     f"{r['build_s']:.2f} | {r['materialise_s']:.2f} |")
    return "\n".join(lines)


def _num(v, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


def _offset(r: dict) -> str:
    e, n = r.get("offset_east_north_m") or (None, None)
    return "-" if e is None else f"{e:+.3f}, {n:+.3f}"


def _scheduler(r: dict) -> str:
    # rows written before --schedulers were local clusters; matching on a GPU is named beside it
    name = r.get("scheduler", "cluster")
    return f"{name}, {r['device']} ({r['device_name']})" if r.get("device") else name


def format_table(rows: list[dict]) -> str:
    head = (
        "| case | scheduler | workers | cells | wall (s) | match (s) | Mcells/s of wall | Mcells/s of matching "
        "| speed-up vs 1 | peak per worker (MiB) | planned per worker (MiB) | peak / planned | peak client (MiB) "
        "| tree PSS (MiB) | NMAD (m) | completeness | offset E, N (m) | NMAD co-registered (m) |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    base = {(r["case"], _scheduler(r)): r for r in rows if r["workers"] == 1 and "match_s" in r}
    for r in rows:
        m = r["measurement"]
        if "match_s" not in r:
            lines.append(f"| {r['case']} | {_scheduler(r)} | {r['workers']} | failed (rc {m['returncode']}) |||||||||||||||")
            continue
        b = base.get((r["case"], _scheduler(r)))
        speed = f"{b['match_s'] / r['match_s']:.2f}" if b else "-"
        planned = r.get("planned_worker_mib")
        plan = f"{planned:.0f}" if planned else "-"
        workers = r.get("scheduler", "cluster") == "cluster"  # threads: no worker process, the client runs the tasks
        per_worker = f"{m['peak_descendant_rss_mib']:.0f}" if workers else "-"
        ratio = f"{m['peak_descendant_rss_mib'] / planned:.2f}" if planned and workers else "-"
        wall_rate = r.get("mcells_per_s_wall", r["cells"] / 1e6 / m["wall_s"])
        lines.append(
            f"| {r['case']} | {_scheduler(r)} | {r['workers']} | {r['cells'] / 1e6:.2f} M | {m['wall_s']:.1f} | "
            f"{r['match_s']:.1f} | {wall_rate:.3f} | {r['mcells_per_s']:.3f} | {speed} | {per_worker} | {plan} | {ratio} | "
            f"{m['peak_root_rss_mib']:.0f} | "
            f"{m['peak_pss_mib'] or float('nan'):.0f} | "
            f"{_num(r['nmad_m'])} | {_num(r['completeness'])} | {_offset(r)} | {_num(r.get('nmad_coregistered_m'))} |"
        )
    return "\n".join(lines)


def scaling_rows(rows: list[dict]) -> list[dict]:
    """Memory against the scene's size, per worker count, for the synthetic
    cases of one run (smallest scene first): the per-worker peak relative to
    the smallest scene's (flat = 1), and the client's growth over the
    smallest scene against one float32 array of the whole scene (the
    client must never hold one: ``holds_scene`` is then False)."""
    out = []
    # per-worker peaks need worker processes; matching on the CPU
    rows = [r for r in rows if r.get("scheduler", "cluster") == "cluster" and not r.get("device")]
    for w in sorted({r["workers"] for r in rows}):
        synth = sorted((r for r in rows if r["workers"] == w and r["case"].startswith("synth") and "match_s" in r),
                       key=lambda r: r["cells"])
        if not synth:
            continue
        first = synth[0]["measurement"]
        for r in synth:
            m = r["measurement"]
            scene_mib = r["cells"] * 4 / 2**20
            growth = m["peak_root_rss_mib"] - first["peak_root_rss_mib"]
            out.append({
                "case": r["case"], "workers": w, "levels": len(r.get("levels") or {}) or None,
                "worker_peak_mib": m["peak_descendant_rss_mib"],
                "worker_peak_vs_smallest": m["peak_descendant_rss_mib"] / first["peak_descendant_rss_mib"],
                "planned_worker_mib": r.get("planned_worker_mib"),
                "client_peak_mib": m["peak_root_rss_mib"], "client_growth_mib": growth,
                "scene_float32_mib": scene_mib, "holds_scene": bool(growth >= scene_mib) if r is not synth[0] else False,
            })
    return out


def format_scaling_table(rows: list[dict]) -> str:
    head = ("| case | workers | peak per worker (MiB) | vs smallest | planned per worker (MiB) | peak client (MiB) "
            "| client growth vs smallest (MiB) | one float32 scene array (MiB) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['workers']} | {r['worker_peak_mib']:.0f} | {r['worker_peak_vs_smallest']:.2f} | "
            f"{_num(r['planned_worker_mib'], '.0f')} | {r['client_peak_mib']:.0f} | {r['client_growth_mib']:+.0f} | "
            f"{r['scene_float32_mib']:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="*", default=["s2p", "synth4096"], help="s2p and/or synth<N> (none: graph only)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--schedulers", nargs="+", default=["threads"], choices=["threads", "cluster"],
                    help="threads: --workers threads of the command's process (tiledsm dsm's default); cluster: a "
                         "local cluster of --workers processes (a --cluster file); each is a row")
    ap.add_argument("--devices", nargs="+", default=["cpu"],
                    help="where matching runs (tiledsm dsm --device): cpu, cuda, ...; each is a row")
    ap.add_argument("--chunk", type=int, default=512)
    ap.add_argument("--levels", type=int, default=None, help="pyramid levels (default: the command's own choice)")
    ap.add_argument("--bounds", type=float, nargs=4, metavar=("XMIN", "YMIN", "XMAX", "YMAX"),
                    help="synthetic cases: run on this part of the truth grid only (see above)")
    ap.add_argument("--graph-sizes", type=int, nargs="*", default=[4096, 8192, 16384],
                    help="grid sides whose graph construction is timed (none: skip)")
    ap.add_argument("--score-max-size", type=int, default=0,
                    help="leave the scoring out for cases of more than N² cells (0: score all)")
    ap.add_argument("--run-dir", default=str(REPO / "runs" / "bench_dsm"))
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "dsm.json"))
    ap.add_argument("--warmup", action="store_true",
                    help="first an untimed two-level 256² run per device (numba's disk caches filled)")
    args = ap.parse_args(argv)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if args.warmup:
        warm_caches(run_dir, sorted({spec.partition("@")[2] or d for spec in args.cases for d in args.devices}))
    rows = []
    for spec in args.cases:
        case, _, only = spec.partition("@")
        for sched in args.schedulers:
            for device in [only] if only else args.devices:
                for w in args.workers:
                    rows.append(run_case(case, w, run_dir, args.chunk, args.timeout, args.bounds, sched, args.levels,
                                         device, args.score_max_size))
                    print(format_table(rows[-1:]).splitlines()[-1], flush=True)
    table = format_table(rows)
    print(table)
    agreement = device_agreement(rows)
    for a in agreement:
        print(f"{a['case']}, {a['workers']} workers, {' vs '.join(a['devices'])}: valid in one only "
              f"{a['valid_in_one_share']:.4%}, heights off by > 1 mm {a['off_1mm_share']:.4%}")
    scaling = scaling_rows(rows)
    if len(scaling) > 1:
        print()
        print(format_scaling_table(scaling))
    held = [r["case"] for r in scaling if r["holds_scene"]]
    if held:
        print(f"the client grew by a whole float32 scene array or more in: {', '.join(held)}", file=sys.stderr)
    graph = graph_rows(run_dir, args.graph_sizes) if args.graph_sizes else []
    if graph:
        print()
        print(format_graph_table(graph))
    result = {
        "benchmark": "dsm",
        "when": _dt.datetime.now().isoformat(timespec="seconds"),
        "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "rows": rows,
        "command": " ".join(sys.argv),
        "table": table,
        "device_agreement": agreement,
        "scaling": scaling,
        "scaling_table": format_scaling_table(scaling) if scaling else None,
        "graph": graph,
        "graph_table": format_graph_table(graph) if graph else None,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1, default=str))
    print(f"wrote {args.json}")
    return 0 if all("match_s" in r for r in rows) and not held else 1


if __name__ == "__main__":
    sys.exit(main())
