"""Semi-global aggregation cost per candidate: narrow bands against a full sweep.

Times :func:`tiledsm.match.sgm.aggregate` (the fast kernel, 8 paths, paths restarting every 64
cells as in the DSM) on synthetic volumes of one DSM task (576 x 576 cells: a 512-cell chunk plus
its halo), in this process, single-threaded (CPU time, the fastest of ``--repeat`` runs):

- ``band``: a finer level's search, ``nvalid`` of 9 to 11 candidates per cell in a volume 30 deep
  (a block is as deep as its widest band; cells under a coarse hole have about 25), bases
  shifting by one label every 50 cells (absolute labels);
- ``sweep``: a coarsest level's full sweep, 116 candidates in every cell.

The costs are uniform random numbers in [0, 2] (ZNCC costs), so both cases do the same arithmetic
per candidate; what differs is the work per cell. Prints ns per candidate (CPU time / (cells x
mean candidates)) and ns per cell, and writes ``benchmarks/results/aggregate.json``.

Usage::

    nice -n 5 .venv/bin/python benchmarks/aggregate.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import write_result  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
CELLS = 576
CASES = {"band": (30, 9, 12), "sweep": (116, 116, 117)}  # depth, nvalid low, high (exclusive)


def volume(depth: int, lo: int, hi: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cost volume, bases and candidate counts of one synthetic task."""
    rng = np.random.default_rng(seed)
    cost = (rng.random((CELLS, CELLS, depth)) * 2).astype(np.float32)
    nvalid = rng.integers(lo, hi, (CELLS, CELLS))
    base = (np.add.outer(np.arange(CELLS), np.arange(CELLS)) // 50).astype(np.int64)
    return cost, base, nvalid


def main(argv=None) -> int:
    from tiledsm.match.sgm import aggregate

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "aggregate.json")
    args = ap.parse_args(argv)
    rows = []
    for name, (depth, lo, hi) in CASES.items():
        cost, base, nvalid = volume(depth, lo, hi)
        aggregate(cost[:8, :8], 0.3, 2.0, base=base[:8, :8], nvalid=nvalid[:8, :8], fast=True)  # compiled
        best = np.inf
        for _ in range(args.repeat):
            t = time.process_time()
            aggregate(cost, 0.3, 2.0, base=base, nvalid=nvalid, fast=True, restart_period=64)
            best = min(best, time.process_time() - t)
        cells = CELLS * CELLS
        mean = float(nvalid.mean())
        rows.append({"case": name, "cells": cells, "depth": depth, "mean_candidates": mean, "cpu_s": best,
                     "ns_per_candidate": best / (cells * mean) * 1e9, "ns_per_cell": best / cells * 1e9})
        r = rows[-1]
        print(f"{name}: {cells} cells, depth {depth}, {mean:.1f} candidates/cell: {best:.3f} s CPU, "
              f"{r['ns_per_candidate']:.1f} ns per candidate, {r['ns_per_cell']:.0f} ns per cell", flush=True)
    write_result(args.json, "aggregate", "benchmarks/aggregate.py", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
