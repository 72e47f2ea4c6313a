"""The CUDA matching kernel against the compiled CPU one, task by task.

Two steps, so that the GPU machine needs no more than numpy, numba and
tiledsm's matching modules:

1. ``--capture DIR`` (any machine): the two tasks of
   ``benchmarks/profile_match.py`` (the middle chunk of the coarsest level,
   a horizontal sweep; the middle chunk of the full-resolution level, a
   band around the level-1 DSM) of a synthetic scene are run as a DSM task
   runs them (:func:`tiledsm.dsm.match_cells`), and the arguments each
   hands to the matching kernel (cost volume, then aggregation and
   winners) are saved, one ``.npz`` per call.
2. ``--tasks DIR`` (a machine with a CUDA GPU): each saved call is run by
   every ``--kernels`` entry (``fast``: the compiled CPU kernel on one
   thread; ``cuda``: :mod:`tiledsm.match.cuda_kernel`), the fastest of
   ``--repeat`` runs after a warm-up (compilation, device set-up) kept,
   split into the cost volume and the aggregation with winners; and the
   winners are compared with the CPU kernel's on the terms of issue 20: the
   share of cells whose validity differs (at most 0.1 %) and the share of
   cells valid in both whose heights differ by more than 1e-3 m (at most
   0.1 %).

   With ``--threads N`` each call is also run by N threads at once, each
   doing ``--repeat`` tasks after a warm-up, as N dask threads feed one
   GPU (or N cores): the row's ``mcells_per_s`` is then all threads' cells
   over the wall time (``threads`` says N). This is the throughput a
   DSM run sees; the single-task rows show a task's latency.

Usage::

    .venv/bin/python benchmarks/cuda_kernel.py --capture runs/cuda_tasks
    python3 benchmarks/cuda_kernel.py --tasks runs/cuda_tasks --kernels fast cuda --threads 16 \\
        --json benchmarks/results/cuda_kernel.json

Prints a markdown table and writes ``--json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent
sys.path.insert(0, str(REPO.parent))

#: the cost-volume arguments saved per call, in the kernels' order
VOLUME_ARGS = ("lat_r", "lat_c", "stride", "k0", "dh", "href", "step", "origin", "nodes0", "win_r", "win_c",
               "cubic", "base", "nvalid", "half", "pair_w")


def capture(work: Path, size: int, chunk: int, levels: int | None = None) -> list[Path]:
    """Run the profiled tasks with a kernel that saves its arguments."""
    sys.path.insert(0, str(REPO))
    import profile_match

    from tiledsm.dsm import match_cells
    from tiledsm.match.kernels import KERNELS, MatchKernel, register_kernel
    from tiledsm.match.sgm import aggregate_best
    from tiledsm.match.sweep import cost_volume

    calls: list[dict] = []

    def volume(imgs, *args, details=None):
        calls.append({"imgs": [np.asarray(im) for im in imgs], **dict(zip(VOLUME_ARGS, args))})
        return cost_volume(imgs, *args, details=details)

    def best(vol, P1, P2, **kw):
        # base and nvalid are the volume's (saved with it)
        calls[-1]["winners"] = {"P1": float(P1), "P2": float(P2), "invalid_cost": float(kw["invalid_cost"]),
                                "origin": [int(o) for o in kw["origin"]], "restart_period": int(kw["restart_period"])}
        return aggregate_best(vol, P1, P2, **kw)

    if "capture" not in KERNELS:
        register_kernel("capture", MatchKernel(volume, None, best=best))
    views, grid, h_range, levels, params = profile_match.setup(work, size, chunk, levels)
    coarse1 = profile_match.coarse_level(views, grid, h_range, levels, params, work) if levels > 1 else None
    params = params.model_copy(update={"match": params.match.model_validate(params.match.model_dump() | {"kernel": "capture"})})
    out = []
    work.mkdir(parents=True, exist_ok=True)
    for name, (geom, cells, search) in profile_match.tasks(views, grid, h_range, levels, params, coarse1).items():
        calls.clear()
        match_cells(views, geom, cells, search, h_range, params)
        for n, call in enumerate(calls):
            path = work / f"{name}_{n}.npz"
            arrays = {f"img{v}": im for v, im in enumerate(call["imgs"])}
            arrays.update({k: np.asarray(call[k]) for k in VOLUME_ARGS if call[k] is not None})
            np.savez_compressed(path, meta=json.dumps({"task": name, "views": len(call["imgs"]),
                                                       "winners": call["winners"]}), **arrays)
            out.append(path)
    return out


def _load(path: Path) -> tuple[str, tuple, dict, dict]:
    z = np.load(path)
    meta = json.loads(str(z["meta"]))
    imgs = [z[f"img{v}"] for v in range(meta["views"])]
    args = []
    for k in VOLUME_ARGS:
        if k not in z:
            args.append(None)
            continue
        a = z[k]
        args.append(a.item() if a.ndim == 0 else (tuple(int(x) for x in a) if k in ("origin", "nodes0") else a))
    win = meta["winners"]
    win.update(origin=tuple(win["origin"]), base=z["base"], nvalid=z["nvalid"])
    return meta["task"], (imgs, *args), win, meta


def run_call(kernel: str, vargs: tuple, wargs: dict, repeat: int) -> tuple[tuple, float, float]:
    """Winners and the fastest cost-volume and aggregation+winners times
    (s) of ``repeat`` runs after a warm-up."""
    from tiledsm.match.kernels import KERNELS

    k = KERNELS[kernel].for_device("cuda") if kernel == "cuda" else KERNELS[kernel]
    sync = (lambda: None)
    if kernel == "cuda":
        from numba import cuda

        sync = cuda.synchronize
    best_v = best_w = float("inf")
    out = None
    for r in range(repeat + 1):
        t0 = time.perf_counter()
        vol = k.cost_volume(*vargs)
        sync()
        t1 = time.perf_counter()
        out = k.winners(vol, **wargs)
        t2 = time.perf_counter()
        del vol
        if r > 0:
            best_v, best_w = min(best_v, t1 - t0), min(best_w, t2 - t1)
    return out, best_v, best_w


def run_threads(kernel: str, vargs: tuple, wargs: dict, repeat: int, threads: int) -> float:
    """Wall seconds of ``threads`` threads each running the call ``repeat``
    times (cost volume, then winners), after one warm-up call each."""
    import threading

    from tiledsm.match.kernels import KERNELS

    k = KERNELS[kernel].for_device("cuda") if kernel == "cuda" else KERNELS[kernel]
    start = threading.Barrier(threads + 1)
    done = threading.Barrier(threads + 1)
    errors: list[BaseException] = []

    def work():
        try:
            k.winners(k.cost_volume(*vargs), **wargs)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)
        start.wait()
        try:
            for _ in range(repeat):
                k.winners(k.cost_volume(*vargs), **wargs)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
        done.wait()

    pool = [threading.Thread(target=work) for _ in range(threads)]
    for t in pool:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    done.wait()
    wall = time.perf_counter() - t0
    for t in pool:
        t.join()
    if errors:
        raise errors[0]
    return wall


def agreement(ref: tuple, other: tuple, step: float) -> dict:
    """Cells whose winner validity differs, and heights (index times the
    step) differing by more than 1e-3 m among cells valid in both."""
    a, b = ref[0], other[0]
    fa, fb = np.isfinite(a), np.isfinite(b)
    both = fa & fb
    dh = np.abs(a[both] - b[both]).astype(np.float64) * step
    return {"valid_differs": float(np.mean(fa != fb)), "off_1mm": float(np.mean(dh > 1e-3)) if dh.size else 0.0,
            "max_dh_m": float(dh.max()) if dh.size else 0.0,
            "cbest_max_diff": float(np.nanmax(np.abs(ref[3] - other[3]))) if both.any() else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", type=Path, help="run the profiled tasks and save their kernel calls here")
    ap.add_argument("--tasks", type=Path, help="time the saved calls found here")
    ap.add_argument("--kernels", nargs="+", default=["fast", "cuda"])
    ap.add_argument("--size", type=int, default=1024, help="scene side, pixels (--capture)")
    ap.add_argument("--chunk", type=int, default=512)
    ap.add_argument("--levels", type=int, help="pyramid levels (--capture; default: as tiledsm dsm picks them)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="also run each call by this many threads at once")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.capture:
        for p in capture(args.capture, args.size, args.chunk, args.levels):
            print(p)
        return 0
    import numba

    if args.tasks is None:
        ap.error("give --capture DIR or --tasks DIR")
    calls = sorted(args.tasks.glob("*.npz"))
    if not calls:
        print(f"cuda_kernel.py: --tasks {args.tasks}: no captured calls (*.npz) there; run --capture first",
              file=sys.stderr)
        return 2
    rows = []
    for path in calls:
        task, vargs, wargs, _ = _load(path)
        ny, nx = vargs[6].shape  # href
        res = {}
        for kernel in args.kernels:
            out, tv, tw = run_call(kernel, vargs, wargs, args.repeat)
            res[kernel] = out
            row = {"task": task, "call": path.stem, "kernel": kernel, "cells": ny * nx,
                   "candidates": int(np.max(vargs[14])), "cost_s": tv, "winners_s": tw, "total_s": tv + tw,
                   "mcells_per_s": ny * nx / (tv + tw) / 1e6}
            if kernel != args.kernels[0]:
                row["agreement"] = agreement(res[args.kernels[0]], out, float(vargs[7]))
            # the process's peak so far: after the first kernel's runs, the
            # growth is what the next one adds (a CUDA context, say)
            row["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            rows.append(row)
        for kernel in args.kernels if args.threads > 1 else ():
            wall = run_threads(kernel, vargs, wargs, args.repeat, args.threads)
            tasks = args.threads * args.repeat
            rows.append({"task": task, "call": path.stem, "kernel": kernel, "threads": args.threads, "tasks": tasks,
                         "cells": ny * nx, "candidates": int(np.max(vargs[14])), "wall_s": wall,
                         "total_s": wall / tasks, "cost_s": float("nan"), "winners_s": float("nan"),
                         "mcells_per_s": tasks * ny * nx / wall / 1e6})
    print("| task | kernel | threads | cells | cost volume (s) | aggregation + winners (s) | s per task | Mcells/s "
          "| validity differs | off > 1 mm |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ag = r.get("agreement", {})
        print(f"| {r['call']} | {r['kernel']} | {r.get('threads', 1)} | {r['cells']} | {r['cost_s']:.4f} | "
              f"{r['winners_s']:.4f} | {r['total_s']:.4f} | {r['mcells_per_s']:.2f} | "
              f"{ag.get('valid_differs', 0):.4%} | {ag.get('off_1mm', 0):.4%} |")
    if args.json:
        device = None
        try:
            from numba import cuda

            name = cuda.get_current_device().name if cuda.is_available() else None
            device = name.decode() if isinstance(name, bytes) else name
        except Exception:  # noqa: BLE001 - no CUDA: the report says so
            device = None
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "benchmark": "cuda_kernel", "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "host": {"machine": platform.machine(), "python": platform.python_version(), "numba": numba.__version__,
                     "gpu": device},
            "command": " ".join(sys.argv), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
