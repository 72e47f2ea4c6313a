"""Memory and time of the ortho correlation from 2k² to 16k² (flat per worker?).

Each size runs in its own process trees, measured by
:mod:`benchmarks._measure` (peak RSS per worker process and of the client).
Two orthos of an analytic band-limited texture (a sum of 48 random
sinusoids, evaluated block by block, so no scene-sized array exists
anywhere), the second moved by a known sub-pixel shift, are first written
as zarr stores (the deformation workflow's ``pre/ortho.zarr`` and
``post/ortho.zarr``; measured apart), then correlated from the stores with
:func:`tiledsm.displace.correlate_orthos` (window 32, step 8, each task
reading its own window) on a local cluster of ``--workers`` processes and
written to a zarr store chunk by chunk, as the workflow does. The recovered
shift's median and NMAD check the result at every size.

``--lazy`` measures the other form instead: the two lazy texture arrays
correlated by ``map_overlap`` (the form before the stores were read
directly), whose rows the JSON keeps under ``lazy_map_overlap``.

Usage::

    nice -n 5 .venv/bin/python benchmarks/displacement_memory.py --sizes 2048 4096 8192 16384 --workers 2

Writes ``benchmarks/results/displacement_memory.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks._measure import measure  # noqa: E402

SHIFT = (0.37, -1.21)  # rows (down), columns (right), pixels
RES = 0.5


def _texture_block(block_info=None, *, dy=0.0, dx=0.0, seed=0):
    """The texture on one block, moved by ``(dy, dx)`` pixels (exact: analytic)."""
    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    rng = np.random.default_rng(seed)
    k = 48
    f = rng.uniform(0.01, 0.25, k)  # cycles per pixel, under Nyquist
    a = rng.uniform(0, 2 * np.pi, k)
    ph = rng.uniform(0, 2 * np.pi, k)
    amp = 40.0 / np.sqrt(k) * (0.05 / f) ** 0.5
    y = (np.arange(r0, r1) - dy)[:, None]
    x = (np.arange(c0, c1) - dx)[None, :]
    out = np.full((r1 - r0, c1 - c0), 1000.0)
    for i in range(k):
        u, v = f[i] * np.cos(a[i]), f[i] * np.sin(a[i])
        out += amp[i] * np.cos(2 * np.pi * (v * y + u * x) + ph[i])
    return out.astype(np.float32)


def _textures(size: int):
    import dask.array as da
    import rioxarray  # noqa: F401
    import xarray as xr
    from affine import Affine

    chunks = (tuple([1024] * (size // 1024)),) * 2
    t = Affine(RES, 0, 500000.0, 0, -RES, 4000000.0)

    def ortho(data):
        d = xr.DataArray(data, dims=("y", "x"), name="ortho",
                         coords={"y": t.f + (np.arange(size) + 0.5) * t.e, "x": t.c + (np.arange(size) + 0.5) * t.a})
        return d.rio.write_crs("EPSG:32631").rio.write_transform(t)

    pre = ortho(da.map_blocks(_texture_block, chunks=chunks, dtype=np.float32, meta=np.empty((0, 0), np.float32)))
    post = ortho(da.map_blocks(_texture_block, chunks=chunks, dtype=np.float32, meta=np.empty((0, 0), np.float32),
                               dy=SHIFT[0], dx=SHIFT[1], name="post"))
    return pre, post


def child(size: int, workers: int, out: Path, phase: str) -> None:
    """One measured run (in its own process): ``make`` the stores,
    ``correlate`` them, or correlate the ``lazy`` arrays by map_overlap."""
    from tiledsm.cluster import ClusterConfig, compute_context
    from tiledsm.displace import CorrelationParams, correlate_orthos
    from tiledsm.io import write_zarr

    t0 = time.perf_counter()
    if phase == "make":
        pre, post = _textures(size)
        with compute_context(ClusterConfig(workers=workers, progress=False)):
            write_zarr(pre, out / "pre.zarr")
            write_zarr(post, out / "post.zarr")
        print(json.dumps({"size": size, "wall_s": time.perf_counter() - t0}))
        return
    if phase == "lazy":
        field = correlate_orthos(*_textures(size), CorrelationParams(), chunk=1024)
    else:
        field = correlate_orthos(out / "pre.zarr", out / "post.zarr", CorrelationParams(), chunk=1024)
    with compute_context(ClusterConfig(workers=workers, progress=False)):
        write_zarr(field, out / "field.zarr")
    wall = time.perf_counter() - t0
    import zarr

    g = zarr.open_group(str(out / "field.zarr"), mode="r")
    # the check reads one row of chunks at a time (the client never holds the field)
    dys, dxs = [], []
    for i in range(0, g["dN"].shape[0], 128):
        dys.append(np.asarray(g["dN"][i:i + 128]).ravel() / -RES)
        dxs.append(np.asarray(g["dE"][i:i + 128]).ravel() / RES)
    dy, dx = np.concatenate(dys), np.concatenate(dxs)

    def nmad(v):
        v = v[np.isfinite(v)]
        return float(1.4826 * np.median(np.abs(v - np.median(v))))

    print(json.dumps({"size": size, "wall_s": wall, "windows": int(dy.size), "valid_share": float(np.isfinite(dy).mean()),
                      "dy_error_median_px": float(np.nanmedian(dy) - SHIFT[0]),
                      "dx_error_median_px": float(np.nanmedian(dx) - SHIFT[1]),
                      "dy_nmad_px": nmad(dy), "dx_nmad_px": nmad(dx)}))


def _row(size: int, args, work: Path, phase: str) -> dict:
    out = work / str(size)
    out.mkdir(parents=True, exist_ok=True)
    log = work / f"{size}_{phase}.log"
    m = measure([sys.executable, __file__, "--child", str(size), "--phase", phase, "--workers", str(args.workers),
                 "--work", str(work)], log=log, cwd=REPO)
    res = json.loads(log.read_text().strip().splitlines()[-1]) if m.ok else {"error": log.read_text()[-2000:]}
    row = {"size": size, "workers": args.workers, "phase": phase,
           "measurement": m.to_dict() if hasattr(m, "to_dict") else vars(m), **res}
    print(f"{size} {phase}: {res}", flush=True)
    return row


def _table(rows: list[dict], title: str) -> None:
    print(f"\n{title}\n| size | windows | wall (s) | ms per window per worker | peak per worker (MiB) | peak client (MiB) "
          "| shift error (px) | NMAD (px) |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['size']}² | failed | | | | | | |")
            continue
        m = r["measurement"]
        print(f"| {r['size']}² | {r['windows']} | {r['wall_s']:.0f} | {1e3 * r['wall_s'] * r['workers'] / r['windows']:.2f} | "
              f"{m['peak_descendant_rss_mib']:.0f} | {m['peak_root_rss_mib']:.0f} | "
              f"{r['dy_error_median_px']:+.4f}, {r['dx_error_median_px']:+.4f} | {r['dy_nmad_px']:.4f}, {r['dx_nmad_px']:.4f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2048, 4096, 8192, 16384])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lazy", action="store_true", help="measure the lazy map_overlap form instead")
    ap.add_argument("--work", default="/tmp/tiledsm_bench_displacement_memory")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "displacement_memory.json"))
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--phase", default="correlate", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    work = Path(args.work)
    if args.child:
        child(args.child, args.workers, work / str(args.child), args.phase)
        return 0
    path = Path(args.json)
    doc = json.loads(path.read_text()) if path.is_file() else {}
    doc.update({"benchmark": "displacement_memory", "host": {"cpus": os.cpu_count()}, "shift_px": SHIFT})
    if args.lazy:
        rows = [_row(size, args, work, "lazy") for size in args.sizes]
        doc["lazy_map_overlap"] = {"when": _dt.datetime.now().isoformat(timespec="seconds"), "rows": rows}
        _table(rows, "lazy orthos, map_overlap")
    else:
        made, rows = [], []
        for size in args.sizes:
            made.append(_row(size, args, work, "make"))
            rows.append(_row(size, args, work, "correlate"))
            shutil.rmtree(work / str(size), ignore_errors=True)  # 2 x 1 GiB at 16384²
        doc.update({"when": _dt.datetime.now().isoformat(timespec="seconds"), "rows": rows, "make_stores": made})
        _table(rows, "stored orthos, each task reads its window")
        print("\nwriting the two stores: " + ", ".join(
            f"{r['size']}² {r.get('wall_s', float('nan')):.0f} s, {r['measurement']['peak_descendant_rss_mib']:.0f} MiB "
            "per worker" for r in made))
    path.write_text(json.dumps(doc, indent=1, default=str))
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
