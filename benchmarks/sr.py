"""Throughput of tiled SR inference vs one bare torch call (overhead of tiling).

For each model (random-initialised networks: the speed does not depend on
the weights) on a synthetic ``size x size`` single-band image:

- ``bare``: one ``model(x)`` call on the whole image (torch, 1 thread);
- ``tiled-1``: ``super_resolve`` with ``chunk``-pixel tiles on the
  synchronous scheduler (one thread);
- ``tiled-2``: the same graph on a ``LocalCluster`` of 2 single-threaded
  worker processes.

Throughput is in output (HR) megapixels per second. Writes a markdown table
and ``benchmarks/results/sr.json``. ``--paddings reflect symmetric`` builds
each CNN with each padding in turn (same run, same image): the cost of the
method's symmetric padding against the reflect padding used before.

Usage: ``python benchmarks/sr.py [--size 256 --chunk 128 --scale 2 --models bicubic srcnn vdsr srmd --paddings reflect symmetric]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import dask
import numpy as np
import torch
import xarray as xr

from tiledsm.sr import build, super_resolve
from tiledsm.sr.infer import sr_array


def _time(fn, repeat: int = 2) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--chunk", type=int, default=128)
    p.add_argument("--scale", type=int, default=2)
    p.add_argument("--models", nargs="+", default=["bicubic", "srcnn", "vdsr", "srmd"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--paddings", nargs="+", default=["symmetric"], help="padding(s) of the CNNs: symmetric, reflect, zeros")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "sr.json"))
    args = p.parse_args(argv)

    torch.set_num_threads(1)
    img = np.random.default_rng(0).uniform(0, 4095, (args.size, args.size)).astype(np.float32)
    hr_mpx = (args.size * args.scale) ** 2 / 1e6
    rows = []
    from distributed import Client, LocalCluster

    os.environ.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    try:
        for name, padding in [(m, pad) for m in args.models for pad in (args.paddings if m != "bicubic" else ["-"])]:
            torch.manual_seed(0)
            model = build(name, scale=args.scale, **({"padding": padding} if padding != "-" else {})).eval()
            kw = {"blur_sigma": 1.0, "noise": 10.0} if model.takes_degradation else {}
            scene = xr.DataArray(img, dims=("y", "x")).chunk(args.chunk)
            lazy = super_resolve(scene, model, args.scale, value_scale=4095.0, **kw)
            bare = _time(lambda: sr_array(img, model, value_scale=4095.0, **kw), args.repeat)
            with dask.config.set(scheduler="synchronous"):
                tiled1 = _time(lambda: lazy.data.compute(), args.repeat)
            tiled2 = _time(lambda: client.compute(lazy.data).result(), args.repeat)
            rows.append({
                "model": name, "padding": padding, "halo_lr_px": model.halo, "bare_s": bare, "tiled1_s": tiled1, "tiled2_s": tiled2,
                "bare_mpx_s": hr_mpx / bare, "tiled1_mpx_s": hr_mpx / tiled1, "tiled2_mpx_s": hr_mpx / tiled2,
            })
            print(rows[-1], flush=True)
    finally:
        client.close()
        cluster.close()
    result = {
        "image_lr": [args.size, args.size], "scale": args.scale, "chunk": args.chunk, "workers": args.workers,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared)",
        "torch": torch.__version__, "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"\nLR {args.size}x{args.size} -> x{args.scale}, tiles {args.chunk} px; HR Mpx/s (higher is better)\n")
    print("| model | padding | halo (LR px) | bare torch | tiled, 1 thread | tiled, %d workers | tiling overhead |" % args.workers)
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['model']} | {r['padding']} | {r['halo_lr_px']} | {r['bare_mpx_s']:.3f} | {r['tiled1_mpx_s']:.3f} | "
              f"{r['tiled2_mpx_s']:.3f} | {r['tiled1_s'] / r['bare_s'] - 1:+.0%} |")
    return result


if __name__ == "__main__":
    main()
