"""The torch matching kernel against the compiled one: time and agreement.

The two tasks of ``benchmarks/profile_match.py`` (the middle chunk of the
coarsest level, a horizontal sweep; the middle chunk of the full-resolution
level, a band around the level-1 DSM) of a synthetic scene, each matched as
a DSM task matches it (:func:`tiledsm.dsm.match_cells`) by the compiled
kernel (``kernel="fast"``, the CPU default) and by the torch kernel on each
``--devices`` entry (``cpu``; ``cuda`` where a GPU is lent). Per task and
kernel: the fastest of ``--repeat`` wall times (after a warm-up run that
compiles and, on a GPU, initialises the device), and the agreement with
the compiled kernel's heights on the issue's terms: the share of cells
whose mask differs (at most 0.1 %) and the share of cells valid in both
whose heights differ by more than 1e-3 m (at most 0.1 %).

Usage::

    .venv/bin/python benchmarks/torch_kernel.py --devices cpu
    .venv/bin/python benchmarks/torch_kernel.py --devices cuda --size 2048 --json benchmarks/results/torch_kernel.json

Prints a markdown table and writes ``--json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO.parent))

import profile_match  # noqa: E402  (the tasks and the scene)
from _measure import write_result  # noqa: E402
from dsm_agreement import agreement  # noqa: E402


def run_task(views, geom, cells, search, h_range, params, repeat: int) -> tuple[np.ndarray, float]:
    from tiledsm.dsm import match_cells

    out = match_cells(views, geom, cells, search, h_range, params)  # warm-up: compile, device set-up
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = match_cells(views, geom, cells, search, h_range, params)
        best = min(best, time.perf_counter() - t0)
    return out[0], best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", nargs="+", default=["cpu"], help="torch devices to run the torch kernel on")
    ap.add_argument("--size", type=int, default=1024, help="scene side, pixels")
    ap.add_argument("--chunk", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--work", default=str(REPO.parent / "runs" / "profile_match"))
    ap.add_argument("--json", default=str(REPO / "results" / "torch_kernel.json"))
    args = ap.parse_args(argv)

    import torch

    from tiledsm.cluster import single_threaded_libraries

    single_threaded_libraries()  # one thread, as in a DSM task
    views, grid, h_range, levels, params = profile_match.setup(Path(args.work), args.size, args.chunk, 2)
    coarse1 = profile_match.coarse_level(views, grid, h_range, levels, params)
    todo = profile_match.tasks(views, grid, h_range, levels, params, coarse1)
    rows = []
    for name, (geom, cells, search) in todo.items():
        fast, t_fast = run_task(views, geom, cells, search, h_range, params, args.repeat)
        rows.append({"task": name, "kernel": "fast", "device": "cpu", "wall_s": t_fast, "cells": list(fast.shape)})
        for device in args.devices:
            match = dataclasses.replace(params.match, kernel="torch", device=device)
            p = dataclasses.replace(params, match=match)
            other, t = run_task(views, geom, cells, search, h_range, p, args.repeat)
            name_dev = torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "CPU"
            rows.append({"task": name, "kernel": "torch", "device": device, "device_name": name_dev, "wall_s": t,
                         "cells": list(other.shape), "vs_fast": t / t_fast, **agreement(fast, other)})
    lines = ["| task | kernel | device | wall (s) | vs fast | masks differ | heights off > 1 mm | within tolerance |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["kernel"] == "fast":
            lines.append(f"| {r['task']} | fast | cpu | {r['wall_s']:.2f} | 1 | - | - | - |")
        else:
            lines.append(f"| {r['task']} | torch | {r['device']} ({r['device_name']}) | {r['wall_s']:.2f} | "
                         f"{r['vs_fast']:.2f}x | {r['mask_differs']:.4%} | {r['heights_off_by_more_than_1mm']:.4%} | "
                         f"{'yes' if r['within_tolerance'] else 'NO'} |")
    table = "\n".join(lines)
    print(table)
    write_result(Path(args.json), "torch_kernel", " ".join(["benchmarks/torch_kernel.py", *(argv or sys.argv[1:])]),
                 rows, torch=torch.__version__, size=args.size, table=table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
