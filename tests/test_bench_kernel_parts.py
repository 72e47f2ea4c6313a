"""benchmarks/kernel_parts.py: its parts time the kernel's own arithmetic.

Oracle: the compiled sweep itself (:func:`tiledsm.match.sweep.cost_volume`)
on a small hand-made block (two views, a sheared projection lattice,
ragged search bands): the benchmark's sampling driver and the kernel's
ZNCC rows must give its volume bit for bit, and the counts it divides by
are those of the block.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.kernel_parts import _Inputs, check_split, measure, row_of, sampling, tracks  # noqa: E402
from tiledsm.match.params import SGVLLParams  # noqa: E402


def _block(ny: int = 24, nx: int = 28, seed: int = 0) -> tuple:
    """``cost_volume`` arguments of a block: views of a smooth random
    texture, image positions moving with the height differently per view."""
    rng = np.random.default_rng(seed)
    stride, nh = 8, 3
    gy, gx = (ny - 1) // stride + 2, (nx - 1) // stride + 2
    t, i, j = np.meshgrid(np.arange(nh), np.arange(gy), np.arange(gx), indexing="ij")
    lat_r = np.stack([i * stride + 12.0 + 0.4 * t * v for v in range(2)]).astype(np.float64)
    lat_c = np.stack([j * stride + 12.0 + 2.5 * t * v for v in range(2)]).astype(np.float64)
    img = rng.random((72, 80)).astype(np.float32)
    img = (img + np.roll(img, 1, 0) + np.roll(img, 1, 1)) * 1000
    imgs = [img, np.roll(img, 2, 1)]
    href = np.zeros((ny, nx))
    base = rng.integers(0, 4, (ny, nx)).astype(np.int64)
    nvalid = rng.integers(2, 9, (ny, nx)).astype(np.int64)
    nvalid[3, 5] = 0  # a cell not searched
    step, dh, k0 = 1.0, 16.0, 0
    return (imgs, lat_r, lat_c, stride, k0, dh, href, step, (0, 0), (0, 0), np.zeros(2), np.zeros(2), True, base,
            nvalid, 2)


def _hull_samples(base, nvalid, half) -> int:
    """Samples per view, counted by brute force: each cell at the union of
    the label ranges of the computed cells (window inside the block) whose
    window holds it."""
    ny, nx = base.shape
    total = 0
    for i in range(ny):
        for j in range(nx):
            lo, hi = None, None
            for a in range(max(half, i - half), min(ny - half, i + half + 1)):
                for b in range(max(half, j - half), min(nx - half, j + half + 1)):
                    if nvalid[a, b] > 0:
                        lo = base[a, b] if lo is None else min(lo, base[a, b])
                        top = base[a, b] + nvalid[a, b] - 1
                        hi = top if hi is None else max(hi, top)
            total += 0 if lo is None else hi - lo + 1
    return total


@pytest.mark.parametrize("seed", [0, 1])
def test_sampling_and_zncc_rows_give_the_kernels_volume(seed):
    task = _Inputs(_block(seed=seed), {})
    assert check_split(task)


def test_the_parts_run_and_count_the_blocks_samples():
    args = _block()
    task = _Inputs(args, {})
    sampling(task)
    tracks(task)
    best = measure(task, SGVLLParams(), repeat=2)
    assert set(best) == {"volume", "sampling", "tracks", "aggregation"}
    assert all(v >= 0 for v in best.values())
    nvalid = args[14]
    assert task.candidates == int(nvalid.sum())
    assert task.samples == 2 * _hull_samples(args[13], nvalid, 2)
    row = row_of("block", task, best, True)
    assert row["candidates_per_cell"] == pytest.approx(nvalid.mean())
    assert sum(row["shares"].values()) == pytest.approx(1.0)
