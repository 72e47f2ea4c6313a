"""Is the DSM of the real pair bit-identical between two versions of the code?

A refactor must not change a single height. This script runs
``tiledsm dsm`` on ``../shared/data/s2p_pair`` (s2p's grid, as
``benchmarks/dsm.py`` does) twice: once with the code of a git revision
(checked out in a temporary worktree) and once with the working tree, then
compares the stored ``height`` arrays cell by cell (NaN where NaN).

Usage::

    .venv/bin/python benchmarks/same_dsm.py --rev b0a8ef9 [--workers 2]

Prints a table and writes ``benchmarks/results/same_dsm.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("TILEDSM_SHARED_DATA", ROOT.parent / "shared" / "data"))
PAIR = SHARED / "s2p_pair"


def run_dsm(code: Path, out: Path, workers: int) -> float:
    """``tiledsm dsm`` on the pair with the package found in ``code``; wall seconds."""
    imgs = [str(PAIR / "input_pair" / f"img_0{k}.tif") for k in (1, 2)]
    cmd = [sys.executable, "-m", "tiledsm", "dsm", *imgs, "--out", str(out),
           "--like", str(PAIR / "expected_output" / "pair" / "dsm.tif"), "--workers", str(workers), "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(code)}
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"tiledsm dsm failed with the code of {code}:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def heights(store: Path) -> np.ndarray:
    import xarray as xr

    with xr.open_zarr(store, consolidated=False) as ds:
        return ds["height"].values


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", required=True, help="git revision to compare the working tree with")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "same_dsm.json"))
    args = ap.parse_args()
    if not PAIR.is_dir():
        raise SystemExit(f"{PAIR}: not found (set TILEDSM_SHARED_DATA)")
    rev = subprocess.run(["git", "rev-parse", "--short", args.rev], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="same_dsm_") as tmp:
        tmp = Path(tmp)
        tree = tmp / "tree"
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), rev], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            t_old = run_dsm(tree, tmp / "old", args.workers)
            t_new = run_dsm(ROOT, tmp / "new", args.workers)
            a, b = heights(tmp / "old" / "dsm.zarr"), heights(tmp / "new" / "dsm.zarr")
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
    same_nan = np.array_equal(np.isnan(a), np.isnan(b))
    both = np.isfinite(a) & np.isfinite(b)
    differ = int((a[both] != b[both]).sum()) + int((np.isnan(a) != np.isnan(b)).sum())
    result = {
        "rev": rev, "working_tree": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                                   capture_output=True, text=True).stdout.strip() + "+changes",
        "shape": list(a.shape), "cells_with_height": int(both.sum()), "cells_differing": differ,
        "nan_masks_equal": bool(same_nan), "max_abs_diff_m": float(np.abs(a[both] - b[both]).max()) if both.any() else 0.0,
        "identical": bool(a.shape == b.shape and differ == 0),
        "wall_s": {"rev": round(t_old, 1), "working_tree": round(t_new, 1)},
        "command": f"benchmarks/same_dsm.py --rev {args.rev} --workers {args.workers}",
    }
    print(f"{'code':<16} {'wall s':>8}\n{rev:<16} {t_old:8.1f}\n{'working tree':<16} {t_new:8.1f}")
    print(f"height arrays {a.shape}: {result['cells_with_height']} cells with a height, "
          f"{differ} differ, max |diff| {result['max_abs_diff_m']} m -> identical: {result['identical']}")
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0 if result["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
