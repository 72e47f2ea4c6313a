"""A matching task's writes into its level store, by many threads at once.

    nice -n 5 .venv/bin/python benchmarks/store_writes.py [--threads 1 2 16] [--repeat 3]

Each task of ``tiledsm dsm``'s level stages writes its block of every
variable and marks it done. This script writes the 64 blocks of a 4096²
store of two float32 variables (``height``, ``confidence``; blocks of
512, Blosc LZ4 after a shuffle) from a pool of ``--threads`` threads, one
task per block, in three ways:

- **block files**: one file per block, compressed and written by the
  task's thread (:class:`tiledsm.io.BlockFiles`, what the stages do since
  2026-11-27), with the block's two counts and the task's mark;
- **zarr, opened once**: a resumable zarr store
  (:meth:`tiledsm.io.ChunkStore.write_block`, the arrays opened once per
  process by :func:`tiledsm.io.open_store_array`; what the stages did
  before, without their three one-cell writes of counts and marks);
- **zarr, opened per write**: the same with ``zarr.open_array`` before
  every write (what they did before 2026-11-27: each opening reads and
  parses the array's metadata through zarr's one I/O thread).

It prints, per way and thread count, the wall time of the 64 tasks
(median of ``--repeat``) and the mean wall time of one task, checks that
every block holds what was written, and writes
``benchmarks/results/store_writes.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import write_result  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def _opened_per_write(store, path, mode="r"):
    import zarr

    return zarr.open_array(store=str(store), path=path, mode=mode)


#: the ways a task's block is written (see the module docstring)
WAYS = ("block files", "zarr, opened once", "zarr, opened per write")


def run_block_files(threads: int, root: Path, size: int = 4096, chunk: int = 512) -> dict:
    """:func:`run` with :class:`tiledsm.io.BlockFiles`."""
    from tiledsm.io import BlockFiles

    store = BlockFiles(root / f"b{threads}{time.perf_counter_ns()}.blocks", ("height", "confidence"), (size, size),
                       chunk)
    store.prepare({"fingerprint": "benchmark", "tasks": list(store.numblocks)})
    blocks = [(i, j) for i in range(store.numblocks[0]) for j in range(store.numblocks[1])]
    values = np.random.default_rng(0).random((2, chunk, chunk)).astype(np.float32)

    def task(ij):
        t0 = time.perf_counter()
        i, j = ij
        store.write_block(i, j, {"height": values[0] + i, "confidence": values[1] + j}, counts=(i, j))
        store.mark_computed(i, j)
        return time.perf_counter() - t0

    t0 = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        task_s = list(pool.map(task, blocks))
    wall = time.perf_counter() - t0
    ok = bool(store.done().all()) and store.computed() == len(blocks) and all(
        np.array_equal(store.read(i * chunk, (i + 1) * chunk, j * chunk, (j + 1) * chunk, "height"), values[0] + i)
        and np.array_equal(store.read(i * chunk, (i + 1) * chunk, j * chunk, (j + 1) * chunk, "confidence"),
                           values[1] + j)
        for i, j in blocks[:: max(1, len(blocks) // 8)])
    return {"wall_s": wall, "task_s": statistics.fmean(task_s), "values_ok": ok}


def run(threads: int, per_write: bool, root: Path, size: int = 4096, chunk: int = 512) -> dict:
    """Write every block of a fresh zarr store from ``threads`` threads: the
    wall seconds, the mean seconds of a task, and whether the values read
    back are the ones written."""
    from unittest import mock

    from tiledsm.geometry.grid import GroundGrid
    from tiledsm.io import create_store, open_product
    from tiledsm.io import stores

    grid = GroundGrid("EPSG:32631", 6e5, 4.8e6, 1.0, size, size, chunk)
    store = create_store(root / f"s{threads}{'p' if per_write else 'o'}{time.perf_counter_ns()}.zarr", grid,
                         {"height": "float32", "confidence": "float32"})
    blocks = [(i, j) for i in range(store.numblocks[0]) for j in range(store.numblocks[1])]
    rng = np.random.default_rng(0)
    values = rng.random((2, chunk, chunk)).astype(np.float32)

    def task(ij):
        t0 = time.perf_counter()
        i, j = ij
        store.write_block(i, j, {"height": values[0] + i, "confidence": values[1] + j})
        return time.perf_counter() - t0

    patch = mock.patch.object(stores, "open_store_array", _opened_per_write) if per_write else mock.MagicMock()
    with patch:
        t0 = time.perf_counter()
        with ThreadPoolExecutor(threads) as pool:
            task_s = list(pool.map(task, blocks))
        wall = time.perf_counter() - t0
    store.finalize()
    ds = open_product(store.path, chunks=None)
    ok = bool(store.is_complete) and all(
        np.array_equal(ds["height"].values[i * chunk:(i + 1) * chunk, j * chunk:(j + 1) * chunk], values[0] + i)
        and np.array_equal(ds["confidence"].values[i * chunk:(i + 1) * chunk, j * chunk:(j + 1) * chunk], values[1] + j)
        for i, j in blocks[:: max(1, len(blocks) // 8)])
    return {"wall_s": wall, "task_s": statistics.fmean(task_s), "values_ok": ok}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2, 16])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "store_writes.json"))
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(dir=REPO / "runs" if (REPO / "runs").is_dir() else None) as tmp:
        for threads in args.threads:
            # the ways alternate within each repeat: load on the machine falls on all of them alike
            runs: dict[str, list] = {way: [] for way in WAYS}
            for _ in range(args.repeat):
                for way in WAYS:
                    runs[way].append(run_block_files(threads, Path(tmp)) if way == WAYS[0]
                                     else run(threads, way == WAYS[2], Path(tmp)))
            for way in WAYS:
                rows.append({"threads": threads, "way": way, "tasks": 64,
                             "wall_s_median": round(statistics.median(r["wall_s"] for r in runs[way]), 4),
                             "task_ms_median": round(1e3 * statistics.median(r["task_s"] for r in runs[way]), 2),
                             "values_ok": all(r["values_ok"] for r in runs[way])})
                print(rows[-1], flush=True)
    files = {r["threads"]: r for r in rows if r["way"] == WAYS[0]}
    for r in rows:
        r["wall_ratio_to_block_files"] = round(r["wall_s_median"] / files[r["threads"]]["wall_s_median"], 3)
    lines = ["| threads | written as | 64 tasks, wall (s) | one task (ms) | wall / block files | values |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['threads']} | {r['way']} | {r['wall_s_median']:.2f} | {r['task_ms_median']:.1f} | "
              f"{r['wall_ratio_to_block_files']:.2f} | {'ok' if r['values_ok'] else '**differ**'} |" for r in rows]
    table = "\n".join(lines)
    print(table)
    write_result(Path(args.json), "store_writes", "benchmarks/store_writes.py " + " ".join(argv or sys.argv[1:]),
                 rows, table=table)
    return 0 if all(r["values_ok"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
