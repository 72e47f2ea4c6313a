"""Benchmark ``tiledsm compare`` on two synthetic DSM files, beside xdem's Nuth & Kääb.

Inputs (made once per size into ``--run-dir``, outside the repository, and
reused by later runs): a DSM of an analytic terrain (a tilt plus 6 plane
waves, 2 m cells, UTM 32N) and a copy sampled 1.6 rows and 2.3 columns
further plus 0.75 m, so the correction to find is ``dx_px = +2.3``,
``dy_px = +1.6`` (4.6 m east, 3.2 m south) and ``dz = -0.75 m``. Both are
written with :func:`tiledsm.io.write_cog`: tiled 512 x 512, DEFLATE with the
floating-point predictor, overviews (what ``tiledsm dsm`` exports).

Per size, in one run on the same machine:

- ``tiledsm compare REF OTHER --out ... --chunks C --no-progress`` with
  ``--workers W --scheduler threads`` (the ``threads`` row of
  ``--schedulers``: W threads of one process, compare's default) or
  ``--cluster FILE`` naming a local cluster of W worker processes (the
  ``cluster`` row), as a user runs it (a subprocess measured by :mod:`benchmarks._measure`:
  wall time, peak RSS of the client process and of the largest worker), the
  per-phase seconds from ``metrics.json`` (``timings_s``) and the shift
  found (error in metres against the truth);
- xdem 0.2.3 ``NuthKaab`` fit + apply + save on the same files
  (``benchmarks/_xdem_nuthkaab.py`` run by the interpreter of xdem's own venv,
  ``--xdem-python``; skipped with a note when absent), measured the same way.

With ``--repeat N`` each size runs N times, tiledsm and xdem alternating (the
load of a shared machine drifts over minutes); the table shows each tool's
fastest run and every wall time is kept in the JSON.

The table gives the wall ratio tiledsm / xdem of each size and each
process's peak against the smallest size of the run (issue 20: the 8192^2
case within 0.5x of xdem's wall, the largest process within 1.25x of the
2048^2 run's). The machine is shared: compare ratios within one run
(``load_before``/``load_after`` are recorded).

Usage::

    nice -n 10 .venv/bin/python benchmarks/compare.py --sizes 2048 8192 16384 [--no-xdem] [--xdem-max-size 8192]

Results: ``benchmarks/results/compare.json`` and ``compare.md``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import measure, scheduler_args  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
TILEDSM = Path(sys.executable).parent / "tiledsm"
XDEM_PYTHON = Path("/work/peers/xdem/venv/bin/python")
XDEM_SCRIPT = Path(__file__).resolve().parent / "_xdem_nuthkaab.py"

RES = 2.0
X0, Y0 = 500_000.0, 4_400_000.0
CRS = "EPSG:32632"
SHIFT_ROWS, SHIFT_COLS, DZ = 1.6, 2.3, 0.75
#: the correction of the other DSM, metres east / north / up
TRUE_DX_M, TRUE_DY_M, TRUE_DZ = SHIFT_COLS * RES, -SHIFT_ROWS * RES, -DZ
_rng = np.random.default_rng(7)
_LAM = _rng.uniform(200.0, 8000.0, 6)
_TH = _rng.uniform(0, np.pi, 6)
_PH = _rng.uniform(0, 2 * np.pi, 6)
_AMP = 0.03 * _LAM


def _terrain_block(block, drow, dcol, dz, block_info=None):
    (r0, r1), (c0, c1) = block_info[None]["array-location"]
    r = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5 + drow
    c = np.arange(c0, c1, dtype=np.float64)[None, :] + 0.5 + dcol
    x, y = RES * c, -RES * r
    z = 1000.0 + 0.01 * x + dz
    for lam, th, ph, a in zip(_LAM, _TH, _PH, _AMP):
        z = z + a * np.sin(2 * np.pi * (x * np.cos(th) + y * np.sin(th)) / lam + ph)
    return z.astype(np.float32)


def lazy_dsm(n: int, chunks: int, name: str, drow=0.0, dcol=0.0, dz=0.0):
    """An n x n DSM computed block by block on demand (dask-backed DataArray)."""
    import dask.array as da
    import rioxarray  # noqa: F401
    import xarray as xr
    from affine import Affine

    data = da.zeros((n, n), chunks=chunks, dtype=np.float32).map_blocks(
        _terrain_block, drow, dcol, dz, dtype=np.float32, meta=np.empty((0, 0), np.float32))
    arr = xr.DataArray(data, dims=("y", "x"),
                       coords={"y": Y0 - RES * (np.arange(n) + 0.5), "x": X0 + RES * (np.arange(n) + 0.5)},
                       attrs={"source": f"synthetic {name} {n}x{n}"})
    return arr.rio.write_crs(CRS).rio.write_transform(Affine(RES, 0, X0, 0, -RES, Y0))


def make_inputs(n: int, run_dir: Path) -> tuple[Path, Path]:
    """The pair of ``n`` x ``n`` DSM files (written once, then reused)."""
    from tiledsm.io import write_cog

    paths = run_dir / f"ref_{n}.tif", run_dir / f"other_{n}.tif"
    for path, shift in zip(paths, ((0.0, 0.0, 0.0), (SHIFT_ROWS, SHIFT_COLS, DZ))):
        if not path.exists():
            write_cog(lazy_dsm(n, 1024, path.stem, *shift), path)
    return paths


def run_tiledsm(n: int, ref: Path, other: Path, run_dir: Path, workers: int, chunks: int, timeout: float,
                scheduler: str = "cluster") -> dict:
    out = run_dir / f"tiledsm_{n}"
    shutil.rmtree(out, ignore_errors=True)
    how = scheduler_args(scheduler, workers, run_dir)
    argv = [str(TILEDSM), "compare", str(ref), str(other), "--out", str(out), *how,
            "--chunks", str(chunks), "--no-progress"]
    m = measure(argv, log=run_dir / f"tiledsm_{n}_{scheduler}.log", timeout=timeout)
    row = {"measurement": m.to_dict()}
    if m.ok:
        metrics = json.loads((out / "metrics.json").read_text())
        c = metrics["coregistration"]
        row.update(
            timings_s=metrics["timings_s"],
            dx_m=c["dx_m"], dy_m=c["dy_m"], dz=c["dz"],
            shift_error_m=max(abs(c["dx_m"] - TRUE_DX_M), abs(c["dy_m"] - TRUE_DY_M)),
            dz_error_m=abs(c["dz"] - TRUE_DZ),
            stable_nmad_m=metrics["statistics"]["stable"]["nmad"],
            products_mib={p.name: round(_size(p) / 2**20, 1) for p in sorted(out.iterdir())},
        )
    shutil.rmtree(out, ignore_errors=True)
    return row


def run_xdem(n: int, ref: Path, other: Path, run_dir: Path, python: Path, timeout: float) -> dict:
    out = run_dir / f"xdem_{n}.tif"
    log = run_dir / f"xdem_{n}.log"
    m = measure([str(python), str(XDEM_SCRIPT), str(ref), str(other), str(out)], log=log, timeout=timeout)
    row = {"measurement": m.to_dict()}
    if m.ok:
        res = json.loads(log.read_text().strip().splitlines()[-1])
        t = res["timings_s"]
        row.update(
            xdem=res["xdem"], timings_s=t, fit_apply_s=t["fit"] + t["apply"],
            dx_m=res["shift_x"], dy_m=res["shift_y"], dz=res["shift_z"],
            shift_error_m=max(abs(res["shift_x"] - TRUE_DX_M), abs(res["shift_y"] - TRUE_DY_M)),
            dz_error_m=abs(res["shift_z"] - TRUE_DZ),
        )
    out.unlink(missing_ok=True)
    return row


def _best(runs: list[dict]) -> dict:
    """The successful run with the shortest wall time (else the first failure)."""
    ok = [r for r in runs if r["measurement"]["returncode"] == 0 and not r["measurement"]["timed_out"]]
    return min(ok, key=lambda r: r["measurement"]["wall_s"]) if ok else runs[0]


def _size(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file()) if p.is_dir() else p.stat().st_size


def _largest(m: dict) -> float:
    return max(m["peak_root_rss_mib"], m["peak_descendant_rss_mib"])


def format_table(rows: list[dict]) -> str:
    head = ("| size | scheduler | tiledsm wall (s) | phases (s) | peak client (MiB) | peak worker (MiB) "
            "| largest vs first size | shift error (m) | xdem wall (s) | xdem fit+apply (s) | xdem peak (MiB) "
            "| xdem shift error (m) | wall tiledsm / xdem | wall tiledsm / xdem fit+apply |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    first = next((_largest(r["tiledsm"]["measurement"]) for r in rows if "timings_s" in r["tiledsm"]), None)
    for r in rows:
        t, x = r["tiledsm"], r.get("xdem") or {}
        tm = t["measurement"]
        if "timings_s" not in t:
            lines.append(f"| {r['size']}² | {r.get('scheduler', 'cluster')} | failed (rc {tm['returncode']}) |" + " |" * 12)
            continue
        ts = t["timings_s"]
        phases = ", ".join(f"{k} {v:.1f}" for k, v in ts.items() if k != "total")
        cells = [f"{r['size']}²", r.get("scheduler", "cluster"), f"{tm['wall_s']:.1f}", phases, f"{tm['peak_root_rss_mib']:.0f}", f"{tm['peak_descendant_rss_mib']:.0f}",
                 f"{_largest(tm) / first:.2f}", f"{t['shift_error_m']:.4f}"]
        if "fit_apply_s" in x:
            xm = x["measurement"]
            cells += [f"{xm['wall_s']:.1f}", f"{x['fit_apply_s']:.1f}", f"{xm['peak_single_rss_mib']:.0f}",
                      f"{x['shift_error_m']:.4f}", f"{tm['wall_s'] / xm['wall_s']:.2f}",
                      f"{tm['wall_s'] / x['fit_apply_s']:.2f}"]
        else:
            note = x.get("note") or (f"failed (rc {x['measurement']['returncode']})" if x else "not run")
            cells += [note, "-", "-", "-", "-", "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2048, 8192])
    ap.add_argument("--chunks", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--schedulers", nargs="+", default=["threads"], choices=["cluster", "threads"],
                    help="tiledsm's: 'threads' (--workers threads of one process, compare's default) and/or "
                         "'cluster' (a local cluster of --workers processes); each is a row, run alternately with xdem")
    ap.add_argument("--run-dir", default="/tmp/tiledsm_bench_compare", help="inputs (kept) and outputs (removed)")
    ap.add_argument("--xdem-python", default=str(XDEM_PYTHON), help="python of a venv holding xdem 0.2.3")
    ap.add_argument("--no-xdem", action="store_true")
    ap.add_argument("--xdem-max-size", type=int, default=8192,
                    help="run xdem only up to this size (it holds both DSMs in memory: ~15 GB at 16384^2)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs per tool and size, alternating tiledsm and xdem; the table shows each tool's fastest")
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "compare.json"))
    args = ap.parse_args(argv)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    xpy = Path(args.xdem_python)
    rows = []
    for n in args.sizes:
        ref, other = make_inputs(n, run_dir)
        row = {"size": n, "cells": n * n, "chunks": args.chunks, "workers": args.workers,
               "inputs": {"ref": str(ref), "other": str(other), "format": "COG (tiled 512, DEFLATE, predictor 3, overviews)",
                          "mib_each": round(ref.stat().st_size / 2**20, 1)}}
        xdem_note = None
        if args.no_xdem or n > args.xdem_max_size:
            xdem_note = "skipped (--no-xdem)" if args.no_xdem else f"skipped (> --xdem-max-size {args.xdem_max_size})"
        elif not xpy.exists():
            xdem_note = f"skipped: {xpy} not found (install xdem==0.2.3 in its own venv)"
        runs: dict[str, list] = {**{s: [] for s in args.schedulers}, "xdem": []}
        for _ in range(args.repeat):  # alternated, so a change of the machine's load hits every tool
            for sched in args.schedulers:
                runs[sched].append(run_tiledsm(n, ref, other, run_dir, args.workers, args.chunks, args.timeout, sched))
            if xdem_note is None:
                runs["xdem"].append(run_xdem(n, ref, other, run_dir, xpy, args.timeout))
        xdem = _best(runs["xdem"]) if runs["xdem"] else {"note": xdem_note}
        for sched in args.schedulers:
            rows.append({**row, "scheduler": sched, "tiledsm": _best(runs[sched]), "xdem": xdem,
                         "tiledsm_walls_s": [round(r["measurement"]["wall_s"], 2) for r in runs[sched]],
                         "xdem_walls_s": [round(r["measurement"]["wall_s"], 2) for r in runs["xdem"]]})
            print(format_table(rows).splitlines()[-1], flush=True)
    table = format_table(rows)
    print(table)
    result = {
        "benchmark": "compare",
        "when": _dt.datetime.now().isoformat(timespec="seconds"),
        "command": " ".join(["benchmarks/compare.py", *(argv if argv is not None else sys.argv[1:])]),
        "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                 "load_avg": os.getloadavg()},
        "truth": {"dx_m": TRUE_DX_M, "dy_m": TRUE_DY_M, "dz_m": TRUE_DZ},
        "repeat": args.repeat,
        "rows": rows,
        "table": table,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1, default=str))
    Path(args.json).with_suffix(".md").write_text(
        f"`{result['command']}` ({result['when']}; fastest of {args.repeat} alternating run(s) per tool)\n\n{table}\n")
    print(f"wrote {args.json}")
    return 0 if all("timings_s" in r["tiledsm"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
