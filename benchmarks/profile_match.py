"""Profile one matching task: share of time per phase of the SGVLL kernel.

Two tasks of a synthetic scene (``tiledsm.synth.make_scene``, GSD 0.5 m,
B/H 0.4, made once into ``--work`` and reused), each run as a DSM task
runs them (:func:`tiledsm.dsm.match_cells`: the cells of its task window, images
read and decimated inside):

- ``coarsest``: the middle chunk of the coarsest pyramid level, which
  searches the whole scene height range (a horizontal sweep);
- ``level0``: the middle chunk of the full-resolution level, searching a
  band around the upsampled level-1 DSM (computed once beforehand, with
  the same kernel, over the whole level).

Each task runs under ``cProfile`` timed by this process's CPU time (the
kernel is single-threaded; other work on a shared machine changes CPU
time far less than wall time), the fastest of ``--repeat`` runs kept;
every function's own time is put in one
phase by its name (:data:`PHASES`): projection (lon/lat, RPC lattice,
per-cell height lines), sampling (image interpolation), cost (ZNCC, cost
volume), aggregation (semi-global paths), wta (winner-take-all, sub-step
refinement, masks), other (image reading, decimation, search band, the
Python between). ``--kernels`` runs the task once per matching kernel
(:data:`tiledsm.match.kernels.KERNELS`, when the package has them) in the
same process, so their ratio is measured under the same load; the kernel's
own report (candidates per cell, timings) is kept too.

Usage::

    nice -n 10 .venv/bin/python benchmarks/profile_match.py --label before
    nice -n 10 .venv/bin/python benchmarks/profile_match.py --label after --kernels reference fast

Prints a markdown table and stores it under ``--label`` in
``benchmarks/results/profile_match.json`` (other labels are kept).
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as _dt
import json
import os
import platform
import pstats
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

#: phase of a function, by its name: exact names, or prefixes (ending in "*")
PHASES: dict[str, tuple[str, ...]] = {
    "projection": ("_lonlat", "project", "rpc_terms", "_poly", "_normalise_ground", "_project*", "transform",
                   "reference_surface", "_lattice*", "_lines*", "_track*"),
    "sampling": ("_sample*", "sample_view", "sample_hull", "_interpolate"),
    "cost": ("_zncc*", "zncc_cost", "mean_zncc_cost", "_scatter", "_cost*", "cost_volume*"),
    "aggregation": ("aggregate*", "_pass*", "_fill_invalid", "_aggregate*"),
    "wta": ("winner_take_all", "_wta*", "remove_speckles", "_speckles"),
}
PHASE_ORDER = ("projection", "sampling", "cost", "aggregation", "wta", "other")


def phase_of(func: str) -> str:
    """The phase of a function name (:data:`PHASES`), else ``"other"``."""
    for phase, names in PHASES.items():
        for n in names:
            if func == n or (n.endswith("*") and func.startswith(n[:-1])):
                return phase
    return "other"


def _scene(work: Path, size: int):
    from tiledsm.synth import make_scene

    d = work / f"scene{size}"
    info = d / "profile_scene.json"
    if not info.exists():
        sc = make_scene(d, size=size, gsd=0.5, bh=0.4, seed=0)
        info.write_text(json.dumps({"views": [str(v) for v in sc.views], "truth": str(sc.truth_dsm),
                                    "height_range": list(sc.height_range)}))
    return json.loads(info.read_text())


def _grid_like(truth: str, chunk: int):
    import rioxarray

    from tiledsm.geometry.grid import GroundGrid

    t = rioxarray.open_rasterio(truth)
    x0, _, _, y0 = t.rio.bounds()
    return GroundGrid(crs=t.rio.crs.to_string(), x0=x0, y0=y0, resolution=abs(t.rio.resolution()[0]),
                      width=t.rio.width, height=t.rio.height, chunk=chunk)


def _layout(geom, grid, params):
    """The level's chunks and ``middle(axis)``: the cells a matching task
    computes for the middle chunk of an axis (the package's layout; one
    from before it: ``task_window``, or the chunk plus the halo)."""
    try:
        from tiledsm.dsm.layout import level_layout
    except ImportError:
        from tiledsm.dsm import level_layout as chunks_of

        chunks = chunks_of(geom.grid.shape, grid.chunk, params)

        def middle(axis):
            k = len(chunks[axis]) // 2
            try:
                from tiledsm.dsm.levels import task_window
            except ImportError:
                start, halo = sum(chunks[axis][:k]), params.halo()
                return max(0, start - halo), min(sum(chunks[axis]), start + chunks[axis][k] + halo)
            return task_window(chunks[axis], k, params)[2:]

        return chunks, middle
    layout = level_layout(geom, grid.chunk, params)
    return layout.chunks, lambda axis: layout.task_window(axis, len(layout.chunks[axis]) // 2)[2:]


def _params(kernel: str | None, base):
    if kernel is None:
        return base
    return base.model_copy(update={"match": base.match.model_validate(base.match.model_dump() | {"kernel": kernel})})


def setup(work: Path, size: int, chunk: int, levels: int | None):
    """Views (relatively corrected), truth grid, height range (tie points,
    as ``tiledsm dsm`` finds it), pyramid levels and the DSM parameters."""
    from tiledsm.dsm import DSMParams, auto_levels, open_views, scene_height_range

    sc = _scene(work, size)
    params = DSMParams(chunk=chunk)
    views = open_views(sc["views"])
    h_range, views, _ = scene_height_range(views, params)
    grid = _grid_like(sc["truth"], chunk)
    levels = levels or auto_levels(views, grid, h_range, params)
    return views, grid, h_range, levels, params


def coarse_level(views, grid, h_range, levels, params, work: Path) -> np.ndarray:
    """The level-1 heights over the whole grid (levels > 1), in process:
    the engine's level stores down to level 1 (a package from before it:
    the plain graph), speckles removed over the whole level."""
    import dask

    with dask.config.set(scheduler="synchronous"):
        try:
            from tiledsm.dsm.layout import level_layout
            from tiledsm.dsm.stages import stage_level
        except ImportError:
            from tiledsm.dsm import level_array, level_geometry, level_layout

            arr = None
            for level in range(levels - 1, 0, -1):
                geom = _geometry(level_geometry, views, grid, level, h_range, params, levels)
                chunks = level_layout(geom.grid.shape, grid.chunk, params)
                arr = level_array(views, geom, chunks, h_range, params, None if arr is None else arr[0]).persist()
            return np.asarray(arr[0].compute())
        import zarr

        from tiledsm.dsm import dsm_fingerprint, level_geometry

        fp = json.dumps(dsm_fingerprint(views, grid, h_range, levels, params), sort_keys=True)
        staged = None
        for level in range(levels - 1, 0, -1):
            geom = level_geometry(views, grid, level, h_range, params, levels)
            staged = stage_level(views, geom, level_layout(geom, grid.chunk, params), h_range, params, staged,
                                 work / "levels", fp)
        staged.tokens.compute()
        from tiledsm.match.sgm import remove_speckles

        store = staged.level.store
        if hasattr(store, "live_path"):  # a package (--src) whose level stores were zarr
            h = np.asarray(zarr.open_array(store=str(store.live_path), path="height", mode="r")[...])
        else:
            h = store.read(0, store.shape[0], 0, store.shape[1], "height")
        layout = staged.level.layout
        return remove_speckles(h, layout.speckle_max_diff, layout.speckle_size) if layout.speckle_size > 1 else h


def _geometry(level_geometry, views, grid, level, h_range, params, levels):
    try:
        return level_geometry(views, grid, level, h_range, params, levels)
    except TypeError:  # a package (--src) from before the coarser sweep step
        return level_geometry(views, grid, level, h_range, params)


def tasks(views, grid, h_range, levels, params, coarse1):
    """``{name: (geom, cells, search)}`` of the two profiled tasks."""
    from tiledsm.dsm import level_geometry
    from tiledsm.match.pyramid import search_from_coarse, search_halo

    out = {}
    top = levels - 1
    geom = _geometry(level_geometry, views, grid, top, h_range, params, levels)
    _, middle = _layout(geom, grid, params)
    out["coarsest"] = (geom, (*middle(0), *middle(1)), None)
    if levels > 1:
        geom0 = level_geometry(views, grid, 0, h_range, params)
        _, middle = _layout(geom0, grid, params)
        r0, r1 = middle(0)
        c0, c1 = middle(1)
        depth = search_halo(params.search)
        # the coarse cells under the fine cells [r0, r1) x [c0, c1) (even starts), grown by depth
        pad = np.pad(coarse1, depth + 1, constant_values=np.nan)
        a0, a1, b0, b1 = r0 // 2, (r1 + 1) // 2, c0 // 2, (c1 + 1) // 2
        block = pad[a0 + 1 : a1 + 1 + 2 * depth, b0 + 1 : b1 + 1 + 2 * depth]
        band = search_from_coarse(block, depth, params.refine_steps * geom0.step, tuple(h_range), params.search)
        search = band[:, r0 - 2 * a0 : r0 - 2 * a0 + r1 - r0, c0 - 2 * b0 : c0 - 2 * b0 + c1 - c0]
        out["level0"] = (geom0, (r0, r1, c0, c1), np.ascontiguousarray(search))
    return out


def profile_task(views, geom, cells, search, h_range, params, repeat: int = 1) -> dict:
    """Profile of the fastest of ``repeat`` runs of one task (a shared
    machine's load only ever adds time)."""
    from tiledsm.dsm import match_cells

    # compile (numba cache) and warm the file cache outside the measurement
    small = (cells[0], min(cells[1], cells[0] + 48), cells[2], min(cells[3], cells[2] + 48))
    s_small = None if search is None else search[:, : small[1] - small[0], : small[3] - small[2]]
    match_cells(views, geom, small, s_small, h_range, params)
    best = None
    for _ in range(repeat):
        # CPU time of this process (the kernel is single-threaded): what
        # other work on a shared machine changes least
        pr = cProfile.Profile(time.process_time)
        t0, c0 = time.perf_counter(), time.process_time()
        pr.enable()
        res = match_cells(views, geom, cells, search, h_range, params)
        pr.disable()
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
        if best is None or cpu < best[0]:
            best = (cpu, wall, pr, res)
    cpu, wall, pr, res = best
    st = pstats.Stats(pr)
    phases = dict.fromkeys(PHASE_ORDER, 0.0)
    funcs = {}
    for (file, line, func), (_, _, tottime, _, _) in st.stats.items():
        phases[phase_of(func)] += tottime
        funcs[func] = funcs.get(func, 0.0) + tottime
    total = sum(phases.values())
    rows, cols = cells[1] - cells[0], cells[3] - cells[2]
    lo_hi = None if search is None else search[1:]
    n_cand = _candidates(h_range, geom.step, lo_hi, search)
    top = sorted(funcs.items(), key=lambda kv: -kv[1])[:12]
    return {
        "level": geom.level, "cells": [rows, cols], "step_m": geom.step, "cpu_s": cpu, "wall_s": wall,
        "profiled_s": total, "phases_s": phases, "shares": {k: v / total for k, v in phases.items()},
        "mean_candidates": n_cand, "mcells_per_cpu_s": rows * cols / 1e6 / cpu,
        "valid": float(np.isfinite(res[0]).mean()), "top_functions_s": dict(top), "repeat": repeat,
    }


def _candidates(h_range, step, lo_hi, search) -> float:
    """Mean candidate heights per searched cell (labels covering each
    cell's band, as the kernel counts them)."""
    if search is None:
        return float(np.ceil((h_range[1] - h_range[0]) / step) + 1)
    href, lo, hi = search
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi >= lo)
    href = np.where(np.isfinite(href), href, np.mean(h_range))
    base = np.floor((lo[ok] - href[ok]) / step + 1e-9)
    top = np.ceil((hi[ok] - href[ok]) / step - 1e-9)
    return float(np.mean(top - base + 1))


def format_table(label: str, rows: dict) -> str:
    head = "| run | task | cells | candidates/cell | CPU (s) | wall (s) | " + " | ".join(PHASE_ORDER) + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for key, r in rows.items():
        shares = " | ".join(f"{100 * r['shares'][p]:.0f} % ({r['phases_s'][p]:.2f} s)" for p in PHASE_ORDER)
        lines.append(f"| {label} | {key} | {r['cells'][0]}x{r['cells'][1]} | {r['mean_candidates']:.1f} | "
                     f"{r['cpu_s']:.2f} | {r['wall_s']:.2f} | {shares} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", required=True, help="name of this measurement in the JSON (e.g. before, after)")
    ap.add_argument("--size", type=int, default=1024, help="scene side, pixels")
    ap.add_argument("--chunk", type=int, default=512, help="chunk side of the grid (the DSM default)")
    ap.add_argument("--levels", type=int, default=2,
                    help="pyramid levels (2: the coarsest is level 1 and level 0 searches a band; 0: automatic)")
    ap.add_argument("--kernels", nargs="*", default=None,
                    help="matching kernels to profile (SGVLLParams.kernel); default: the package's default only")
    ap.add_argument("--repeat", type=int, default=3, help="runs per task; the fastest is reported")
    ap.add_argument("--src", default=None,
                    help="folder holding the tiledsm package to profile instead of the working tree's, e.g. "
                         "the committed code: git archive HEAD tiledsm | tar -x -C /tmp/src-head")
    ap.add_argument("--work", default=str(REPO / "runs" / "profile_match"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "profile_match.json"))
    args = ap.parse_args(argv)
    if args.src:
        sys.path.insert(0, str(Path(args.src).resolve()))
    import tiledsm

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    views, grid, h_range, levels, params = setup(work, args.size, args.chunk, args.levels)
    t0 = time.perf_counter()
    coarse1 = coarse_level(views, grid, h_range, levels, params, work) if levels > 1 else None
    t_coarse = time.perf_counter() - t0
    todo = tasks(views, grid, h_range, levels, params, coarse1)
    kernels = args.kernels or [None]
    results = {}
    for kernel in kernels:
        p = _params(kernel, params)
        for name, (geom, cells, search) in todo.items():
            key = name if kernel is None else f"{name}/{kernel}"
            results[key] = profile_task(views, geom, cells, search, h_range, p, args.repeat)
            print(format_table(args.label, {key: results[key]}).splitlines()[-1], flush=True)
    table = format_table(args.label, results)
    print(table)
    for key, r in results.items():
        print(f"{key}: top functions (own time, s): "
              + ", ".join(f"{k} {v:.2f}" for k, v in list(r["top_functions_s"].items())[:8]))
    speedups = {}
    if args.kernels and len(kernels) > 1:
        ref = kernels[0]
        for kernel in kernels[1:]:
            for name in todo:
                speedups[f"{name}: {kernel} vs {ref}"] = (
                    results[f"{name}/{ref}"]["cpu_s"] / results[f"{name}/{kernel}"]["cpu_s"]
                )
        for k, v in speedups.items():
            print(f"speed-up (CPU time) {k}: {v:.2f}x")
    path = Path(args.json)
    store = json.loads(path.read_text()) if path.exists() else {"benchmark": "profile_match", "runs": {}}
    store["runs"][args.label] = {
        "when": _dt.datetime.now().isoformat(timespec="seconds"),
        "command": " ".join(["benchmarks/profile_match.py", *(argv if argv is not None else sys.argv[1:])]),
        "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                 "load_avg": os.getloadavg()},
        "package": str(Path(tiledsm.__file__).parent),
        "scene": {"size": args.size, "chunk": args.chunk, "levels": levels, "height_range_m": list(h_range),
                  "coarse_levels_s": t_coarse},
        "tasks": results, "speedups": speedups, "table": table,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(store, indent=1, default=float))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
