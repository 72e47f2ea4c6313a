"""Where a matching task's kernel time goes: the compiled sweep split into
its parts, in nanoseconds per sample and per candidate.

The fast kernel fuses sampling and ZNCC in one compiled call per block
(:func:`tiledsm.match.sweep.cost_volume`), so a profiler sees one function
(``benchmarks/profile_match.py``: ``_sweep``). This script takes the two
tasks ``profile_match.py`` profiles (the middle chunk of the coarsest
level, a horizontal sweep over the whole height range, and of level 0, a
band around the coarser DSM; a synthetic scene of ``--size`` pixels),
captures the inputs of their cost volume (a kernel registered for the
purpose, :func:`tiledsm.match.kernels.register_kernel`, records them and
calls the fast kernel), then times on those inputs, in turns within each
repeat (process CPU time, the fastest of ``--repeat`` kept):

- ``volume``: the whole cost volume, as a task computes it;
- ``sampling``: the same rows sampled by the same compiled row function
  (``_sample_row``: the vertical lines' image positions and the bicubic
  samples of every view), without the ZNCC;
- ``tracks``: the vertical lines' image positions alone (``_track``, at
  the same labels), without interpolating the images;
- ``aggregation``: the 8 semi-global paths and each cell's winner on the
  volume (:func:`tiledsm.match.sgm.aggregate_best`).

Derived: interpolation = sampling - tracks; ZNCC and the rest of the
sweep = volume - sampling. Rates are per (cell, view, label) sample taken
(each cell is sampled at the labels its window's cells search, the
``n_samples`` of :func:`~tiledsm.match.sweep.sample_plan`) and per
(cell, candidate) of the volume. The parts' volume is checked equal to the
kernel's bit for bit: the split times the task's own arithmetic.

Usage::

    nice -n 5 .venv/bin/python benchmarks/kernel_parts.py [--size 4096] [--repeat 7]

Writes ``benchmarks/results/kernel_parts.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks._measure import write_result  # noqa: E402
from tiledsm.match.sampling import lattice_cell  # noqa: E402
from tiledsm.match.sweep import _sample_row, _track  # noqa: E402

PARTS = ("volume", "sampling", "tracks", "aggregation")


@nb.njit(nogil=True, cache=True)
def _sample_rows(imgs, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c, cubic, lo, hi,
                 ring, yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts):
    """The sampling of ``tiledsm.match.sweep._sweep``: every row of every
    view into the ring's slots, no ZNCC."""
    wsz = ring.shape[1]
    for r in range(href.shape[0]):
        for v in range(len(imgs)):
            _sample_row(imgs[v], lat_r[v], lat_c[v], stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r[v],
                        win_c[v], cubic, r, lo, hi, ring[v, r % wsz], yb, xb, sb, iyb, ixb, wyb, wxb, cells, starts)


@nb.njit(nogil=True, cache=True)
def _track_rows(nv, lat_r, lat_c, stride, k0, dh, href, step, gi0, gj0, n0i, n0j, win_r, win_c, lo, hi, yb, xb):
    """The image positions ``_sample_row`` tracks (each cell at its labels
    ``lo..hi``), for every row and view, without interpolating."""
    ny, nx = href.shape
    _, _, gy, gx = lat_r.shape
    total = 0.0
    for r in range(ny):
        for v in range(nv):
            i0, fy = lattice_cell(gi0 + r, stride, n0i, gy)
            for j in range(nx):
                m = hi[r, j] - lo[r, j] + 1
                if m <= 0:
                    continue
                j0, fx = lattice_cell(gj0 + j, stride, n0j, gx)
                _track(lat_r[v], lat_c[v], i0, j0, fy, fx, k0, dh, href[r, j], step, lo[r, j], win_r[v], win_c[v],
                       yb[:m], xb[:m])
                total += yb[0]
    return total  # kept, so the tracks are not optimised away


class _Inputs:
    """A task's cost-volume arguments as :func:`~tiledsm.match.sweep.cost_volume`
    takes them, in the types its compiled sweep is called with."""

    def __init__(self, args: tuple, kwargs: dict):
        from tiledsm.match.sweep import sample_plan, view_pairs

        (imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid,
         half) = args[:16]
        self.args, self.kwargs = args, {k: v for k, v in kwargs.items() if k != "details"}
        self.imgs = tuple(np.ascontiguousarray(im, np.float32) for im in imgs)
        self.lat_r = np.ascontiguousarray(lat_r, np.float64)
        self.lat_c = np.ascontiguousarray(lat_c, np.float64)
        self.stride, self.k0, self.dh, self.step = int(stride), int(k0), float(dh), float(step)
        self.href = np.ascontiguousarray(href, np.float64)
        self.origin, self.nodes0 = (int(origin[0]), int(origin[1])), (int(nodes0[0]), int(nodes0[1]))
        self.win_r, self.win_c = np.asarray(win_r, np.float64), np.asarray(win_c, np.float64)
        self.cubic, self.half = bool(cubic), int(half)
        self.base = np.ascontiguousarray(base, np.int64)
        self.nvalid = np.ascontiguousarray(nvalid, np.int64)
        details: dict = {}
        self.lo, self.hi, self.ns = sample_plan(self.base, self.nvalid, self.half, details)
        self.samples = details["n_samples"] * len(self.imgs)
        pairs, self.pair_w = view_pairs(len(self.imgs), args[16] if len(args) > 16 else kwargs.get("pair_w"))
        self.pair_u = np.array([p[0] for p in pairs], np.int64)
        self.pair_v = np.array([p[1] for p in pairs], np.int64)
        self.candidates = int(self.nvalid.sum())

    def scratch(self, ring: bool = True):
        """The sweep's scratch (:func:`~tiledsm.match.sweep._sweep_scratch`),
        after the ring of sampled rows (``None`` without ``ring``)."""
        from tiledsm.match.sweep import _sweep_scratch

        nv, nx = len(self.imgs), self.href.shape[1]
        rows = np.full((nv, 2 * self.half + 1, nx, self.ns), np.nan, np.float32) if ring else None
        return rows, _sweep_scratch(nv, len(self.pair_u), nx, self.ns, max(1, int(self.nvalid.max())), self.half)

    def geometry(self) -> tuple:
        return (self.lat_r, self.lat_c, self.stride, self.k0, self.dh, self.href, self.step, *self.origin,
                *self.nodes0, self.win_r, self.win_c)


def volume(task: _Inputs) -> np.ndarray:
    from tiledsm.match.sweep import cost_volume

    return cost_volume(*task.args, **task.kwargs)


def sampling(task: _Inputs) -> None:
    ring, s = task.scratch()
    _sample_rows(task.imgs, *task.geometry(), task.cubic, task.lo, task.hi, ring, *s[:9])


def tracks(task: _Inputs) -> None:
    _, s = task.scratch(ring=False)
    _track_rows(len(task.imgs), *task.geometry(), task.lo, task.hi, s[0], s[1])


def aggregation(task: _Inputs, vol: np.ndarray, match) -> None:
    from tiledsm.match.sgm import aggregate_best

    aggregate_best(vol, match.P1, match.P2, base=task.base, nvalid=task.nvalid, invalid_cost=match.invalid_cost,
                   origin=task.origin, restart_period=match.path_period)


def capture(views, todo, h_range, params) -> dict:
    """``{task: _Inputs}``: the cost-volume arguments of each task of
    ``todo`` (:func:`benchmarks.profile_match.tasks`), recorded by a kernel
    registered for it while the task runs as a DSM task runs it."""
    from tiledsm.dsm import match_cells
    from tiledsm.match.kernels import KERNELS, register_kernel

    name = "kernel-parts-capture"
    seen: list = []
    if name not in KERNELS:
        fast = KERNELS["fast"]

        def recording(*args, **kwargs):
            seen.append((args, kwargs))
            return fast.cost_volume(*args, **kwargs)

        register_kernel(name, dataclasses.replace(fast, cost_volume=recording))
    p = params.model_copy(update={"match": params.match.model_copy(update={"kernel": name})})
    out = {}
    for task, (geom, cells, search) in todo.items():
        seen.clear()
        match_cells(views, geom, cells, search, h_range, p)
        (args, kwargs), = seen
        out[task] = _Inputs(args, kwargs)
    return out


def measure(task: _Inputs, match, repeat: int) -> dict:
    """Fastest process CPU time of each part over ``repeat`` turns."""
    ref = volume(task)  # compiled and warm
    sampling(task)
    tracks(task)
    aggregation(task, ref, match)
    times = {p: [] for p in PARTS}
    for _ in range(repeat):
        for part in PARTS:
            c0 = time.process_time()
            if part == "volume":
                vol = volume(task)
            elif part == "sampling":
                sampling(task)
            elif part == "tracks":
                tracks(task)
            else:
                aggregation(task, ref, match)
            times[part].append(time.process_time() - c0)
    if not np.array_equal(vol.view(np.uint32), ref.view(np.uint32)):
        raise SystemExit("the volume differs between two runs of the kernel")
    best = {p: min(t) for p, t in times.items()}
    return best


def check_split(task: _Inputs) -> bool:
    """Whether the sampling driver's ring plus the kernel's own ZNCC rows
    give the kernel's volume bit for bit (the parts time the task's own
    arithmetic)."""
    from tiledsm.match.sweep import empty_volume
    from tiledsm.match.zncc_rows import zncc_row

    ring, s = task.scratch()
    nv = len(task.imgs)
    vol = empty_volume(task.nvalid, max(1, int(task.nvalid.max())))
    eps = float(task.kwargs.get("eps", 1e-6))
    wsz = 2 * task.half + 1
    for r in range(task.href.shape[0]):
        for v in range(nv):
            _sample_row(task.imgs[v], task.lat_r[v], task.lat_c[v], task.stride, task.k0, task.dh, task.href,
                        task.step, *task.origin, *task.nodes0, task.win_r[v], task.win_c[v], task.cubic, r, task.lo,
                        task.hi, ring[v, r % wsz], *s[:9])
        i = r - task.half
        if i >= task.half:
            zncc_row(ring, i, task.half, task.lo, task.base, task.nvalid, task.pair_u, task.pair_v, task.pair_w,
                     eps, vol, *s[9:])
    return bool(np.array_equal(vol.view(np.uint32), volume(task).view(np.uint32)))


def row_of(name: str, task: _Inputs, best: dict, same: bool) -> dict:
    ns = 1e9
    interp = best["sampling"] - best["tracks"]
    zncc = best["volume"] - best["sampling"]
    kernel = best["volume"] + best["aggregation"]
    return {
        "task": name, "cells": list(task.href.shape), "views": len(task.imgs),
        "candidates_per_cell": task.candidates / task.href.size,
        "samples_per_cell_and_view": task.samples / len(task.imgs) / task.href.size,
        "seconds": best, "split_equals_kernel": same,
        "ns_per_sample": {"tracks": best["tracks"] / task.samples * ns, "interpolation": interp / task.samples * ns,
                          "sampling": best["sampling"] / task.samples * ns},
        "ns_per_candidate": {"sampling": best["sampling"] / task.candidates * ns,
                             "zncc_and_rest": zncc / task.candidates * ns,
                             "aggregation_and_winners": best["aggregation"] / task.candidates * ns,
                             "kernel": kernel / task.candidates * ns},
        "shares": {"tracks": best["tracks"] / kernel, "interpolation": interp / kernel, "zncc_and_rest": zncc / kernel,
                   "aggregation_and_winners": best["aggregation"] / kernel},
    }


def table(rows: list[dict]) -> str:
    head = ("| task | cells | candidates / cell | samples / cell and view | tracks (ns / sample) | "
            "interpolation (ns / sample) | ZNCC and the rest (ns / candidate) | aggregation and winners "
            "(ns / candidate) | kernel (ns / candidate) | shares: tracks, interpolation, ZNCC, aggregation |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        s, c, sh = r["ns_per_sample"], r["ns_per_candidate"], r["shares"]
        lines.append(
            f"| {r['task']} | {r['cells'][0]}x{r['cells'][1]} | {r['candidates_per_cell']:.1f} | "
            f"{r['samples_per_cell_and_view']:.1f} | {s['tracks']:.1f} | {s['interpolation']:.1f} | "
            f"{c['zncc_and_rest']:.1f} | {c['aggregation_and_winners']:.1f} | {c['kernel']:.1f} | "
            + ", ".join(f"{100 * sh[k]:.0f} %" for k in ("tracks", "interpolation", "zncc_and_rest",
                                                          "aggregation_and_winners")) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from benchmarks.profile_match import coarse_level, setup, tasks

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=1024, help="scene side, pixels")
    ap.add_argument("--chunk", type=int, default=512, help="chunk side of the grid (the DSM default)")
    ap.add_argument("--repeat", type=int, default=7, help="turns; the fastest of each part is kept")
    ap.add_argument("--work", default=str(REPO / "runs" / "profile_match"),
                    help="where the scene is made once (shared with profile_match.py)")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "kernel_parts.json"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    views, grid, h_range, levels, params = setup(work, args.size, args.chunk, 2)
    coarse1 = coarse_level(views, grid, h_range, levels, params, work)
    captured = capture(views, tasks(views, grid, h_range, levels, params, coarse1), h_range, params)
    rows = []
    for name, task in captured.items():
        same = check_split(task)
        rows.append(row_of(name, task, measure(task, params.match, args.repeat), same))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
        if not same:
            raise SystemExit(f"{name}: the split's volume differs from the kernel's")
    text = table(rows)
    print(text)
    command = " ".join(["benchmarks/kernel_parts.py", *(argv if argv is not None else sys.argv[1:])])
    write_result(Path(args.json), "kernel_parts", command, rows, table=text,
                 scene={"size": args.size, "chunk": args.chunk, "levels": levels, "height_range_m": list(h_range)},
                 repeat=args.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
