"""Accuracy of two vs three views: the multi-view sweep, plain and parallax-weighted.

A synthetic scene with three views (``tiledsm synth --views 3``: B/H 0.4
between views 0 and 1, 0.2 from each to the middle view 2) is matched on its
truth grid with views 0-1 only, then with all three views scoring each
candidate height by the mean ZNCC of the three pairs, plainly averaged and
weighted by each pair's squared parallax (``SGVLLParams.weight_pairs``).
Scores against the truth on the cells visible in every view: NMAD, RMSE and
median error (metres) on the common cells, where every case has a height
(:func:`tiledsm.workflows.sr_scores.compare_on_common`), so a case cannot score
better by leaving holes; completeness is each case's own share of the
visible truth cells.

Usage::

    nice -n 10 .venv/bin/python benchmarks/views.py [--size 512] [--seed 1]

Writes ``benchmarks/results/views.json`` and prints a markdown table. Match
times depend on the machine's load: each row records the 1-minute load
average before and after its match (``load_before``, ``load_after``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def score_cases(heights: dict[str, np.ndarray], truth: np.ndarray, visible: np.ndarray) -> tuple[dict[str, dict], dict]:
    """Each case's DSM against the truth, all on the cells where every case has a height.

    Parameters
    ----------
    heights : dict of str to numpy.ndarray
        DSM of each case on the truth grid (metres; NaN = no height).
    truth : numpy.ndarray
        True heights (metres; NaN = unknown).
    visible : numpy.ndarray
        bool, cells visible in every view (the evaluated cells, with a true height).

    Returns
    -------
    rows : dict of str to dict
        Per case: ``nmad_m``, ``rmse_m``, ``median_m`` (metres, on the common
        cells), ``scored`` (common cells scored), ``completeness`` (own
        share of the evaluated cells, a fraction) and ``valid`` (own cells
        with a height).
    common : dict
        ``count``, ``cells``, ``fraction``, ``dsms`` of the common cells
        (see :func:`tiledsm.workflows.sr_scores.compare_on_common`).
    """
    from tiledsm.workflows.sr_scores import compare_on_common

    res = compare_on_common(heights, truth, visible)
    rows = {name: {"nmad_m": s["nmad"], "rmse_m": s["rmse"], "median_m": s["median"], "scored": s["count"],
                   "completeness": s["completeness"], "valid": s["valid"]} for name, s in res["scores"].items()}
    return rows, res["common"]


def markdown_table(rows: list[dict], common: dict) -> str:
    """The printed table: one row per case (``case``, ``match_s`` seconds and
    the keys of :func:`score_cases`), under a line giving the common cells."""
    from tiledsm.workflows.sr_scores import common_cells_line

    table = [common_cells_line(common, "the visible truth"), "",
             "| case | NMAD (m) | RMSE (m) | median (m) | completeness | match (s) |", "|---|---|---|---|---|---|"]
    table += [f"| {r['case']} | {r['nmad_m']:.3f} | {r['rmse_m']:.3f} | {r['median_m']:+.3f} | "
              f"{100 * r['completeness']:.1f} % | {r['match_s']:.1f} |" for r in rows]
    return "\n".join(table)


def main(argv: list[str] | None = None) -> int:
    from tiledsm.cluster import ClusterConfig
    from tiledsm.dsm import DSMParams, dsm_from_pair
    from tiledsm.io.grids import grid_like
    from tiledsm.io import open_product
    from tiledsm.match.sgvll import SGVLLParams
    from tiledsm.workflows.common import reference_on_grid, write_dsm_products
    from tiledsm.synth import make_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "views.json"))
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="tiledsm_views_"))
    scene = make_scene(work / "scene", size=args.size, gsd=0.5, bh=0.4, seed=args.seed, views=3)
    grid = grid_like(scene.truth_dsm, chunk=256)
    cases = [
        ("views 0-1", scene.views[:2], True),
        ("3 views, plain mean ZNCC", scene.views, False),
        ("3 views, parallax²-weighted ZNCC", scene.views, True),
    ]
    timings, heights = {}, {}  # per case: match seconds and 1-min load averages; heights (m)
    for name, views, weighted in cases:
        params = DSMParams(chunk=256, match=SGVLLParams(weight_pairs=weighted))
        ds, _ = dsm_from_pair(*views, grid=grid, params=params)
        out = work / name.replace(" ", "_").replace(",", "").replace("²", "2")
        load_before, t0 = os.getloadavg()[0], time.perf_counter()
        write_dsm_products(ds, out, cluster=ClusterConfig(workers=args.workers, progress=False), cog=False, quicklook=False)
        timings[name] = {"match_s": time.perf_counter() - t0, "load_before": load_before, "load_after": os.getloadavg()[0]}
        height = open_product(out / "dsm.zarr")["height"]
        heights[name] = height.values
        print(f"{name}: matched in {timings[name]['match_s']:.1f} s", flush=True)
    truth = reference_on_grid(scene.truth_dsm, height).values
    visible = reference_on_grid(scene.visible_mask, height).values > 0.5
    scores, common = score_cases(heights, truth, visible)
    rows = [{"case": name, **timings[name], **scores[name]} for name in heights]
    table = markdown_table(rows, common)
    print(table)
    doc = {"benchmark": "views", "scene": {"size": args.size, "seed": args.seed, "bh_pairs": scene.bh_pairs},
           "common": common, "rows": rows, "table": table}
    Path(args.json).write_text(json.dumps(doc, indent=1, default=str))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
