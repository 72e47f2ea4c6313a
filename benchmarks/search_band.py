"""A finer level's search band from the coarser heights: its two Gaussian means
over the cells they serve against over the whole window.

    nice -n 5 .venv/bin/python benchmarks/search_band.py [--dsm OUT/dsm.zarr] [--repeat 3]

:func:`tiledsm.match.pyramid.search_from_coarse` turns a finer task's window
of coarser heights into its reference surface and band: a NaN-aware
Gaussian mean (``smooth``), and where that finds no height, a wider one
(``fill_sigma``). Since 2026-11-27 the smoothing is computed over the
cells the band interpolates grown by its radius, and the wider mean over
the holes' bounding box grown by its radius, instead of both over the
whole window (``cropped``). This script takes a DSM that ``tiledsm dsm`` made (default: the
4096² synthetic scene's run of ``benchmarks/dsm.py``), averages it 2 x 2
into a stand-in for its coarser level (NaN where any cell is), and runs
every level-0 task window of the engine (chunks of 512, the engine's
coarse depth) both ways, in turn, ``--repeat`` times; it prints the CPU
seconds of each (fastest repeat), checks the bands are equal bit for bit,
and writes ``benchmarks/results/search_band.json``.
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


def whole_window(coarse: np.ndarray, depth: int, margin: float, h_range, params) -> np.ndarray:
    """:func:`~tiledsm.match.pyramid.search_from_coarse` with both means
    over the whole window (the arithmetic before the crops)."""
    from tiledsm.match.pyramid import _band, _nan_mean

    c = np.asarray(coarse, np.float64)
    valid = np.isfinite(c)
    ref = _nan_mean(c, valid, params.smooth, params.truncate)
    ref = np.where(np.isfinite(ref), ref, _nan_mean(c, valid, params.fill_sigma, params.truncate))
    ny, nx = c.shape[0] - 2 * depth, c.shape[1] - 2 * depth
    out = np.empty((3, 2 * ny, 2 * nx), np.float32)
    _band(ref, valid, depth, float(margin), float(params.hole_factor), float(h_range[0]), float(h_range[1]), out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dsm", default=str(REPO / "runs" / "ref" / "synth4096_w2_threads" / "dsm.zarr"),
                    help="a dsm.zarr made by tiledsm dsm")
    ap.add_argument("--chunk", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "search_band.json"))
    args = ap.parse_args(argv)
    from tiledsm.dsm import DSMParams
    from tiledsm.dsm.layout import _coarse_depth
    from tiledsm.io import open_product
    from tiledsm.match.pyramid import search_from_coarse

    if not Path(args.dsm).exists():
        raise SystemExit(f"--dsm {args.dsm}: not found (run benchmarks/dsm.py --cases synth4096 first)")
    h = np.asarray(open_product(args.dsm)["height"].values, np.float64)
    ny, nx = (h.shape[0] // 2) * 2, (h.shape[1] // 2) * 2
    coarse = h[:ny, :nx].reshape(ny // 2, 2, nx // 2, 2).mean(axis=(1, 3))
    params = DSMParams(chunk=args.chunk)
    depth = _coarse_depth(params)
    half = args.chunk // 2
    pad = np.pad(coarse, depth, constant_values=np.nan)
    h_range = (float(np.nanmin(h)) - 10.0, float(np.nanmax(h)) + 10.0)
    windows = [pad[a : a + half + 2 * depth, b : b + half + 2 * depth]
               for a in range(0, coarse.shape[0] - half + 1, half) for b in range(0, coarse.shape[1] - half + 1, half)]
    ways = {"whole window": lambda w: whole_window(w, depth, 2.5, h_range, params.search),
            "cropped": lambda w: search_from_coarse(w, depth, 2.5, h_range, params.search)}
    cpu = {name: [] for name in ways}
    equal = True
    for _ in range(args.repeat):
        got = {}
        for name, fn in ways.items():
            t = time.process_time()
            got[name] = [fn(w) for w in windows]
            cpu[name].append(time.process_time() - t)
        equal &= all(np.array_equal(a, b, equal_nan=True) for a, b in zip(*got.values()))
    best = {name: min(v) for name, v in cpu.items()}
    rows = [{"way": name, "windows": len(windows), "cpu_s": round(best[name], 3),
             "ms_per_window": round(1e3 * best[name] / len(windows), 2),
             "ratio_to_whole_window": round(best[name] / best["whole window"], 3)} for name in ways]
    holes = float(np.isnan(coarse).mean())
    lines = [f"{len(windows)} level-0 task windows of {Path(args.dsm).parent.name} (coarser stand-in "
             f"{coarse.shape[0]}x{coarse.shape[1]}, {100 * holes:.1f} % NaN, depth {depth}); bands equal bit for bit: "
             f"{'yes' if equal else '**no**'}", "",
             "| Gaussian means over | CPU (s) | per window (ms) | / whole window |", "|---|---|---|---|"]
    lines += [f"| {r['way']} | {r['cpu_s']:.2f} | {r['ms_per_window']:.1f} | {r['ratio_to_whole_window']:.2f} |"
              for r in rows]
    table = "\n".join(lines)
    print(table)
    write_result(Path(args.json), "search_band", "benchmarks/search_band.py " + " ".join(argv or sys.argv[1:]), rows,
                 table=table, dsm=str(args.dsm), nan_share=round(holes, 4), bit_equal=bool(equal))
    return 0 if equal else 1


if __name__ == "__main__":
    raise SystemExit(main())
