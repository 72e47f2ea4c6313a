"""Write and read times and sizes of a DSM's 512² blocks under zarr codecs.

    .venv/bin/python benchmarks/store_codec.py [--dsm PATH/dsm.zarr] [--repeat 3]

Reads 16 blocks of ``height`` and ``confidence`` from a DSM store made by
``tiledsm dsm`` (default: the 4096² synthetic scene's run of
``benchmarks/dsm.py``, ``runs/bench_dsm/synth4096_w2_threads/dsm.zarr``),
writes them into fresh zarr v3 arrays with each codec, reads them back
(checking the values round-trip), and prints per block the write and read
times (best of ``--repeat``, one thread) and the stored size as a fraction
of the raw float32 bytes. The codec of
:func:`tiledsm.io.codecs.store_compressors` is the row ``blosc-lz4-shuffle``.
Writes ``benchmarks/results/store_codec.json``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def codecs() -> dict:
    from zarr.codecs import BloscCodec

    from tiledsm.io.codecs import store_compressors

    return {
        "zarr-default (zstd0)": "auto",
        "none": None,
        "blosc-lz4-shuffle": store_compressors(),
        "blosc-zstd1-shuffle": (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"),),
    }


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and f.name != "zarr.json")


def time_codec(blocks: list[np.ndarray], compressors, repeat: int) -> dict:
    import zarr

    n, side = len(blocks), blocks[0].shape[0]
    per = int(np.ceil(np.sqrt(n)))
    best_w = best_r = np.inf
    for _ in range(repeat):
        where = Path(tempfile.mkdtemp(prefix="codec-"))
        try:
            a = zarr.create_array(store=str(where), shape=(per * side, per * side), chunks=(side, side), dtype="float32",
                                  fill_value=np.nan, compressors=compressors)
            t = time.perf_counter()
            for k, b in enumerate(blocks):
                a[(k // per) * side:(k // per + 1) * side, (k % per) * side:(k % per + 1) * side] = b
            best_w = min(best_w, (time.perf_counter() - t) / n)
            t = time.perf_counter()
            back = [np.asarray(a[(k // per) * side:(k // per + 1) * side, (k % per) * side:(k % per + 1) * side])
                    for k in range(n)]
            best_r = min(best_r, (time.perf_counter() - t) / n)
            if not all(np.array_equal(x, y, equal_nan=True) for x, y in zip(blocks, back)):
                raise SystemExit("a codec did not round-trip the values")
            ratio = _size(where) / sum(b.nbytes for b in blocks)
        finally:
            shutil.rmtree(where, ignore_errors=True)
    return {"write_ms": best_w * 1e3, "read_ms": best_r * 1e3, "size_ratio": ratio}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dsm", type=Path, default=REPO / "runs" / "bench_dsm" / "synth4096_w2_threads" / "dsm.zarr")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "store_codec.json")
    args = ap.parse_args()
    import zarr

    if not args.dsm.exists():
        raise SystemExit(f"{args.dsm}: no DSM store (run benchmarks/dsm.py --cases synth4096 first, or pass --dsm)")
    group = zarr.open_group(str(args.dsm), mode="r")
    side = 512
    rows = {}
    for var in ("height", "confidence"):
        arr = group[var]
        H, W = arr.shape
        picks = [(r, c) for r in np.linspace(0, H - side, 4).astype(int) for c in np.linspace(0, W - side, 4).astype(int)]
        blocks = [np.ascontiguousarray(arr[r:r + side, c:c + side], np.float32) for r, c in picks]
        for name, comp in codecs().items():
            rows.setdefault(name, {})[var] = time_codec(blocks, comp, args.repeat)
    print(f"{'codec':24s} {'variable':11s} {'write ms':>9s} {'read ms':>8s} {'size':>6s}")
    for name, per_var in rows.items():
        for var, r in per_var.items():
            print(f"{name:24s} {var:11s} {r['write_ms']:9.1f} {r['read_ms']:8.1f} {r['size_ratio']:6.2f}")
    doc = {"date": _dt.datetime.now().isoformat(timespec="seconds"), "dsm": str(args.dsm), "block": side,
           "blocks_per_variable": 16, "repeat": args.repeat, "cpus": os.cpu_count(), "zarr": zarr.__version__,
           "rows": rows}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
