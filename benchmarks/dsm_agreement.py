"""Cell-by-cell agreement of two DSMs on the same grid (matched on the CPU
and on a device), on issue 20's terms.

The share of cells whose mask differs (a height in one, none in the
other; at most 0.1 %), the share of cells with a height in both whose
heights differ by more than 1 mm (at most 0.1 %), the largest difference,
and whether the two are identical (NaN where both have none).

Usage::

    .venv/bin/python benchmarks/dsm_agreement.py CPU/dsm.tif GPU/dsm.tif benchmarks/results/NAME.json

e.g. the DSMs of ``benchmarks/dsm.py --cases s2p --devices cpu cuda``
(``runs/bench_dsm/s2p_w2_threads/dsm.tif`` and ``..._cuda/dsm.tif``).
Prints and writes the JSON.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import rasterio


def agreement(fast: np.ndarray, other: np.ndarray, tol_m: float = 1e-3) -> dict:
    """Mask and height agreement of two height arrays (NaN = no height)."""
    a, b = np.isfinite(fast), np.isfinite(other)
    both = a & b
    off = float(np.mean(np.abs(fast[both] - other[both]) > tol_m)) if both.any() else 0.0
    mask = float(np.mean(a != b))
    return {"mask_differs": mask, "heights_off_by_more_than_1mm": off, "within_tolerance": mask <= 1e-3 and off <= 1e-3,
            "max_abs_diff_m": float(np.max(np.abs(fast[both] - other[both]))) if both.any() else 0.0}


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        raise SystemExit(__doc__)
    first, second, out = argv
    arrays = []
    for path in (first, second):
        with rasterio.open(path) as src:
            arrays.append(src.read(1, masked=True).filled(np.nan).astype(np.float64))
    if arrays[0].shape != arrays[1].shape:
        raise SystemExit(f"{second}: {arrays[1].shape} cells, {first} has {arrays[0].shape}: not the same grid")
    res = {"cpu": first, "device": second, "cells": int(arrays[0].size),
           "valid_cpu": int(np.isfinite(arrays[0]).sum()), "valid_device": int(np.isfinite(arrays[1]).sum()),
           **agreement(*arrays), "identical": bool(np.array_equal(*arrays, equal_nan=True))}
    text = json.dumps(res, indent=1)
    print(text)
    with open(out, "w") as f:
        f.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
