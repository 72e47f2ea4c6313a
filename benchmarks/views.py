"""Accuracy of two vs three views: the multi-view sweep, plain and parallax-weighted.

A synthetic scene with three views (``tiledsm synth --views 3``: B/H 0.4
between views 0 and 1, 0.2 from each to the middle view 2) is matched on its
truth grid with views 0-1 only, then with all three views scoring each
candidate height by the mean ZNCC of the three pairs, plainly averaged and
weighted by each pair's squared parallax (``SGVLLParams.weight_pairs``).
Scores against the truth on the cells visible in every view: NMAD, RMSE,
completeness.

Usage::

    nice -n 10 .venv/bin/python benchmarks/views.py [--size 512] [--seed 1]

Writes ``benchmarks/results/views.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def score(height: np.ndarray, truth: np.ndarray, visible: np.ndarray) -> dict:
    d = (height - truth)[visible & np.isfinite(truth)]
    ok = d[np.isfinite(d)]
    return {
        "nmad_m": float(1.4826 * np.median(np.abs(ok - np.median(ok)))),
        "rmse_m": float(np.sqrt(np.mean(ok**2))),
        "completeness": float(np.isfinite(d).mean()),
    }


def main(argv: list[str] | None = None) -> int:
    from tiledsm.cluster import ClusterConfig
    from tiledsm.dsm import DSMParams, dsm_from_pair
    from tiledsm.geometry.grid import GroundGrid
    from tiledsm.io import open_product
    from tiledsm.match.sgvll import SGVLLParams
    from tiledsm.pipelines import _reference_on_grid, write_dsm_products
    from tiledsm.synth import make_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "views.json"))
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="tiledsm_views_"))
    scene = make_scene(work / "scene", size=args.size, gsd=0.5, bh=0.4, seed=args.seed, views=3)
    grid = GroundGrid.like(scene.truth_dsm, chunk=256)
    cases = [
        ("views 0-1", scene.views[:2], True),
        ("3 views, plain mean ZNCC", scene.views, False),
        ("3 views, parallax²-weighted ZNCC", scene.views, True),
    ]
    rows = []
    for name, views, weighted in cases:
        params = DSMParams(chunk=256, match=SGVLLParams(weight_pairs=weighted))
        ds, _ = dsm_from_pair(*views, grid=grid, params=params)
        out = work / name.replace(" ", "_").replace(",", "").replace("²", "2")
        t0 = time.perf_counter()
        write_dsm_products(ds, out, cluster=ClusterConfig(workers=args.workers, progress=False), cog=False, quicklook=False)
        wall = time.perf_counter() - t0
        height = open_product(out / "dsm.zarr")["height"]
        truth = _reference_on_grid(scene.truth_dsm, height).values
        visible = _reference_on_grid(scene.visible_mask, height).values > 0.5
        rows.append({"case": name, "match_s": wall, **score(height.values, truth, visible)})
        print(rows[-1], flush=True)
    table = ["| case | NMAD (m) | RMSE (m) | completeness | match (s) |", "|---|---|---|---|---|"]
    table += [f"| {r['case']} | {r['nmad_m']:.3f} | {r['rmse_m']:.3f} | {100 * r['completeness']:.1f} % | {r['match_s']:.1f} |" for r in rows]
    print("\n".join(table))
    doc = {"benchmark": "views", "scene": {"size": args.size, "seed": args.seed, "bh_pairs": scene.bh_pairs}, "rows": rows,
           "table": "\n".join(table)}
    Path(args.json).write_text(json.dumps(doc, indent=1, default=str))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
