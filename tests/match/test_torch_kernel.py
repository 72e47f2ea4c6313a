"""The torch matching kernel (``kernel="torch"``, here on the CPU) against
the compiled one (``kernel="fast"``): the same arithmetic in the same
floating-point types and order, so the same cost volume, aggregated costs
and heights, bit for bit. On a CUDA device the issue's tolerance applies
(masks within 0.1 %, heights within 1e-3 m on 99.9 % of the cells),
which :func:`_agree` checks here and ``benchmarks/torch_kernel.py``
measures on a device."""

import numpy as np
import pytest

from tiledsm.match import torch_kernel
from tiledsm.match.sgm import aggregate
from tiledsm.match.sgvll import SGVLLParams, match_block

from match_synthetic import CRS, band_with_holes, make_scene, scene_grid


def _volume(rng, shape, nd):
    vol = rng.random((*shape, nd)).astype(np.float32) * 2
    vol[rng.random(vol.shape) < 0.05] = np.nan
    base = rng.integers(-3, 4, shape)
    base[10:12] += 20  # jumps farther than the candidates
    nvalid = rng.integers(1, nd + 1, shape)
    nvalid[rng.random(shape) < 0.03] = 0  # gaps: the paths restart after them
    return vol, base, nvalid


@pytest.mark.parametrize("nd", [1, 2, 9])
def test_torch_aggregation_equals_the_compiled_one(nd):
    """Bit for bit: invalid costs, label shifts (some beyond the
    candidates), absent candidates, gaps, restart lines, a grid origin."""
    rng = np.random.default_rng(nd)
    vol, base, nvalid = _volume(rng, (37, 29), nd)
    for kw in ({}, {"origin": (5, 70), "restart_period": 16}):
        S0 = aggregate(vol, 0.3, 2.0, base=base, nvalid=nvalid, invalid_cost=1.0, fast=True, **kw)
        S1 = torch_kernel.aggregate(vol, 0.3, 2.0, base=base, nvalid=nvalid, invalid_cost=1.0, **kw)
        # +inf exactly where a cell lacks the candidate (measured: 97 / 73 / 55 % finite at depth 1 / 2 / 9)
        np.testing.assert_array_equal(np.isfinite(S0), np.arange(nd) < nvalid[..., None])
        np.testing.assert_array_equal(S1, S0)
    with pytest.raises(ValueError, match="guide"):
        torch_kernel.aggregate(vol, 0.3, 2.0, guide=np.zeros((37, 29), np.float32))


def _both(images, rpcs, gx, gy, lo, hi, params=None, **kw):
    out = {}
    for kernel in ("fast", "torch"):
        d: dict = {}
        p = SGVLLParams(kernel=kernel, **(params or {}))
        h, c = match_block(images, rpcs, None, gx, gy, CRS, lo, hi, p, details=d, **kw)
        out[kernel] = (h, c, d)
    return out


def _agree(fast, torch, tol_m=1e-3):
    """The issue's tolerance: masks differ on at most 0.1 % of the cells,
    heights within ``tol_m`` on at least 99.9 % of those valid in both."""
    mask_diff = np.mean(np.isfinite(fast) != np.isfinite(torch))
    both = np.isfinite(fast) & np.isfinite(torch)
    close = np.mean(np.abs(fast[both] - torch[both]) <= tol_m) if both.any() else 1.0
    return mask_diff <= 1e-3 and close >= 0.999


@pytest.mark.parametrize("tilts, interpolation", [((0.4, -0.4), "cubic"), ((0.4, 0.0, -0.4), "cubic"),
                                                  ((0.4, -0.4), "linear")], ids=["2 views", "3 views", "bilinear"])
def test_torch_kernel_matches_as_the_compiled_one(tilts, interpolation):
    """A block of a synthetic scene, per-cell bands around a surface (some
    wider, some cells not searched) on a grid origin: the same heights and
    confidence, bit for bit, hence within the issue's tolerance."""
    sc = make_scene(tilts=tilts, seed=2)
    gx, gy, truth, lo, hi, kw = band_with_holes(sc, slice(20, 90), slice(10, 90), (slice(30, 40), slice(50, 65)))
    out = _both(sc.images, sc.rpcs, gx, gy, lo, hi, params={"interpolation": interpolation}, **kw)
    (h0, c0, d0), (h1, c1, d1) = out["fast"], out["torch"]
    # measured: 86.4-86.8 % of the cells, median error 0.049-0.069 m
    assert np.isfinite(h0).mean() > 0.85
    assert np.nanmedian(np.abs(h0 - truth)) < 0.08
    np.testing.assert_array_equal(h1, h0)
    np.testing.assert_array_equal(c1, c0)
    assert d1["n_samples"] == d0["n_samples"] and _agree(h0, h1)


def test_torch_cost_volume_of_a_horizontal_sweep():
    """The whole range at every cell (the coarsest level's sweep): the
    volumes and aggregated costs themselves are equal, NaN and masked
    entries included."""
    from tiledsm.match.kernels import KERNELS, MatchKernel

    seen: dict = {}

    def keep(name, fn):
        def run(*args, **kw):
            seen[name] = fn(*args, **kw)
            return seen[name]
        return run

    for kernel in ("fast", "torch"):
        k = KERNELS[kernel].for_device("cpu")
        KERNELS[f"keep-{kernel}"] = MatchKernel(keep(f"vol-{kernel}", k.cost_volume), keep(f"S-{kernel}", k.aggregate))
    try:
        sc = make_scene(tilts=(0.4, -0.4), seed=5)
        gx, gy = scene_grid(sc)
        d: dict = {}
        for kernel in ("fast", "torch"):
            match_block(sc.images, sc.rpcs, None, gx[:60], gy[:50], CRS, 85.0, 125.0,
                        SGVLLParams(kernel=f"keep-{kernel}"), details=d)
    finally:
        KERNELS.pop("keep-fast")
        KERNELS.pop("keep-torch")
    assert d["n_candidates"] == 65
    vol = seen["vol-fast"]
    # measured: 85.9 % valid, 14.1 % NaN (the block's border and flat windows)
    assert np.isnan(vol).any() and np.isfinite(vol).mean() > 0.85
    np.testing.assert_array_equal(seen["vol-torch"], vol)
    np.testing.assert_array_equal(seen["S-torch"], seen["S-fast"])


def test_agreement_check_fails_on_drift():
    """:func:`_agree` is what a device run is held to: it fails on 0.2 % of
    the cells off by 1 cm, or on 0.2 % of the masks flipped."""
    rng = np.random.default_rng(1)
    h = rng.normal(100.0, 5.0, (100, 100)).astype(np.float32)
    off = h.copy()
    off.flat[:20] += 0.01
    flipped = h.copy()
    flipped.flat[:20] = np.nan
    assert _agree(h, h.copy()) and not _agree(h, off) and not _agree(h, flipped)
    small = h.copy()
    small.flat[:5] += 0.01  # 0.05 %: within the tolerance
    assert _agree(h, small)


def test_device_is_checked():
    with pytest.raises(ValueError, match="CPU only"):
        SGVLLParams(device="cpu:0")
    with pytest.raises(ValueError, match="not a torch device"):
        SGVLLParams(kernel="torch", device="gpu7")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            SGVLLParams(kernel="torch", device="cuda")
