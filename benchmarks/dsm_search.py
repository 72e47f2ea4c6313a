"""How a finer pyramid level searches: levels, band width and candidate labels on the real pair.

Runs :func:`tiledsm.dsm.dsm_from_pair` on ``s2p_pair`` on the grid of s2p's DSM (its ROI, 0.5 m)
once per variant of :class:`tiledsm.dsm.params.DSMParams` (2 threads of this process) and scores
each DSM against s2p's DSM on the cells both have: NMAD and RMSE (m) of the error, the share of
cells off by more than 10 m from the median error, and the completeness (share of the reference's
cells with a height). The variants:

- ``levels=1``: one full-resolution sweep over the whole height range (134 candidates on s2p's grid);
- ``levels=2`` with *relative* labels (``SearchParams.relative_labels``: candidates ``h_ref + k
  step`` around the smoothed coarse DSM), with the coarse smoothing ``smooth`` 1 and 3 cells;
- ``levels=2`` with *absolute* labels (the scene-wide lattice ``k step``, the default; see
  :class:`tiledsm.match.pyramid.SearchParams`), band ``refine_steps`` 4 and 3, smooth 1 and 3, the
  coarse sweep at twice its level's step (``DSMParams.sweep_step_factor``, the default), at it, or
  at three times it.

Usage::

    nice -n 5 .venv/bin/python benchmarks/dsm_search.py [--data ../shared/data]

Writes ``benchmarks/results/dsm_search.json`` and prints the table. Wall times are of this process
(2 threads, the scheduler of ``dask.config``), not of the whole command, after one unscored run
(compiled kernels loaded).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import write_result  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def _variants():
    from tiledsm.match.pyramid import SearchParams

    return [
        ("1 level", {"levels": 1}),
        ("2 levels, relative labels, smooth 1", {"levels": 2, "refine_steps": 4,
                                                 "search": SearchParams(relative_labels=True)}),
        ("2 levels, relative labels, smooth 3", {"levels": 2, "refine_steps": 4,
                                                 "search": SearchParams(relative_labels=True, smooth=3.0)}),
        ("2 levels, absolute labels, band 4 steps (the default)", {"levels": 2, "refine_steps": 4,
                                                                   "search": SearchParams(relative_labels=False)}),
        ("2 levels, absolute labels, coarse sweep at the level's own step", {"levels": 2, "refine_steps": 4,
                                                                            "sweep_step_factor": 1.0,
                                                                            "search": SearchParams(relative_labels=False)}),
        ("2 levels, absolute labels, coarse sweep at three times its step", {"levels": 2, "refine_steps": 4,
                                                                            "sweep_step_factor": 3.0,
                                                                            "search": SearchParams(relative_labels=False)}),
        ("2 levels, absolute labels, band 3 steps", {"levels": 2, "refine_steps": 3,
                                                     "search": SearchParams(relative_labels=False)}),
        ("2 levels, absolute labels, smooth 3", {"levels": 2, "refine_steps": 4,
                                                 "search": SearchParams(relative_labels=False, smooth=3.0)}),
    ]


def score(height: np.ndarray, ref: np.ndarray) -> dict:
    """Error statistics of ``height`` against ``ref`` (NaN = none), metres."""
    from tiledsm.compare.coreg import nmad

    e = height - ref
    ok = np.isfinite(e)
    e = e[ok]
    med = float(np.median(e))
    return {"nmad_m": nmad(e), "rmse_m": float(np.sqrt(np.mean(e**2))),
            "gt10_pct": float(np.mean(np.abs(e - med) > 10) * 100),
            "completeness": float(ok.sum() / np.isfinite(ref).sum())}


def main(argv=None) -> int:
    import dask
    import rasterio

    from tiledsm.dsm import dsm_from_pair
    from tiledsm.dsm.params import DSMParams
    from tiledsm.io import grid_like

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data")))
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "dsm_search.json")
    args = ap.parse_args(argv)
    pair = args.data / "s2p_pair"
    images = [pair / "input_pair" / "img_01.tif", pair / "input_pair" / "img_02.tif"]
    reference = pair / "expected_output" / "pair" / "dsm.tif"
    missing = [str(p) for p in [*images, reference] if not p.is_file()]
    if missing:
        raise SystemExit(f"missing input data: {', '.join(missing)}; pass --data")
    with rasterio.open(reference) as src:
        ref = src.read(1, masked=True).astype(np.float64).filled(np.nan)
    def dsm(kw: dict) -> np.ndarray:
        ds, _ = dsm_from_pair(str(images[0]), str(images[1]), grid=grid_like(reference),
                              params=DSMParams(chunk=512, **kw))
        with dask.config.set(scheduler="threads", num_workers=2):
            return ds["height"].values.astype(np.float64)

    # one unscored run first: loading the compiled kernels and the first
    # reads are not charged to the first variant
    dsm(_variants()[0][1])
    rows = []
    for label, kw in _variants():
        t = time.perf_counter()
        height = dsm(kw)
        rows.append({"variant": label, "params": {k: repr(v) for k, v in kw.items()},
                     "seconds": time.perf_counter() - t, **score(height, ref)})
        r = rows[-1]
        print(f"{label}: NMAD {r['nmad_m']:.3f} m, RMSE {r['rmse_m']:.3f} m, > 10 m {r['gt10_pct']:.3f} %, "
              f"completeness {r['completeness'] * 100:.1f} %, {r['seconds']:.1f} s", flush=True)
    write_result(args.json, "dsm_search", "benchmarks/dsm_search.py", rows, data=str(pair), reference=str(reference))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
