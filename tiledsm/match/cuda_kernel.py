"""The SGVLL matching kernel as compiled CUDA kernels (numba's CUDA target).

The heavy steps of :func:`tiledsm.match.sgvll.match_block` on an NVIDIA
GPU, one launch per step over the whole block instead of tensor
operations in Python loops:

1. **Samples** (:func:`_sample_kernel`): one thread per (cell, label of its
   sample hull, :func:`~tiledsm.match.sweep.sample_hull`) computes the
   image position of the cell's vertical line at that label (bilinear on
   the projection lattice's ground nodes, linear in height between its
   height nodes) and the bicubic (Keys, a = -0.75) or bilinear sample of
   every view there.
2. **Costs** (:func:`_zncc_kernel`): one thread per (cell, candidate) adds
   the window's samples at the candidate's absolute label in the order of
   :func:`tiledsm.match.cost.zncc_cost` (column sums top to bottom, then
   columns left to right, float64) and scores ``1 - ZNCC`` (the weighted
   mean over view pairs with three or more views).
3. **Paths** (:func:`_path_kernel`): one thread block per path line of a
   direction walks the line cell by cell; its threads update the cell's
   candidates together (the stay / one-label / ``P2`` transitions from
   the predecessor's path costs at the label shift between the two
   cells), and a block-wide minimum gives the next step its reference.
   The 8 directions run one after another, each adding its path costs to
   ``S`` in the compiled kernel's order (:mod:`tiledsm.match.paths`).
4. **Winners** (:func:`_winner_kernel`): one thread per cell, the rule of
   :func:`tiledsm.match.winner.best_of_cell`.

The volume never leaves the device: :func:`cost_volume` returns it as a
:class:`DeviceVolume`, which :func:`best` takes. The arithmetic is the
CPU kernel's, step for step and in the same floating-point types; run by
numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, tests) it gives the
CPU kernel's volume and winners bit for bit. On a GPU the compiler may
contract a product and a sum into one fused multiply-add, so samples and
costs can differ in their last bits (heights by far less than a
millimetre; ``benchmarks/cuda_kernel.py`` measures the agreement).

The module imports ``numba.cuda`` only when a kernel is first used, so
CPU runs never initialise CUDA. Selected by ``SGVLLParams(kernel="cuda",
device="cuda")``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from tiledsm.match.sweep import sample_plan, view_pairs

__all__ = ["DeviceVolume", "aggregate", "best", "check_device", "cost_volume", "memory_info"]

def _simulated() -> bool:
    from numba import config

    return bool(config.ENABLE_CUDASIM)


#: threads of a 1-D launch's blocks (samples, costs, winners); the
#: simulator runs each thread as a Python thread: fewer there
_THREADS = 128
_SIM_THREADS = 16

#: the 8 path directions ``(di, dj)`` (a cell's predecessor is ``(i - di,
#: j - dj)``) in the order the compiled kernel sums them into ``S``: the
#: forward sweep's in-row path then its three row-crossing paths (from
#: columns ``j + 1, j, j - 1`` of the row above), then the same backward
#: (:func:`tiledsm.match.paths._pass_fast`)
DIRECTIONS = ((0, 1), (1, -1), (1, 0), (1, 1), (0, -1), (-1, -1), (-1, 0), (-1, 1))


def _cuda():
    from numba import cuda

    return cuda


def check_device(device: str) -> None:
    """Raise :class:`ValueError` naming ``device`` when this kernel cannot
    run there (not ``cuda`` or ``cuda:N``, no CUDA GPU visible to numba, no
    such index)."""
    index = _device_index(device)
    cuda = _cuda()
    if not cuda.is_available():
        raise ValueError(f"device {device!r}: numba sees no CUDA GPU here (the 'cuda' kernel needs one)")
    if index >= len(cuda.gpus):
        raise ValueError(f"device {device!r}: only {len(cuda.gpus)} CUDA device(s) here")


def memory_info(device: str) -> tuple[int, int]:
    """``(free, total)`` bytes of the GPU ``device``."""
    with _Selected(device) as cuda:
        free, total = cuda.current_context().get_memory_info()
    return int(free), int(total)


def _device_index(device: str) -> int:
    name, _, idx = str(device).partition(":")
    if name != "cuda" or (idx and not idx.isdigit()):
        raise ValueError(f"device {device!r}: the 'cuda' kernel runs on cuda or cuda:N devices")
    return int(idx or 0)


class _Selected:
    """Context: the numba CUDA device ``device`` made current."""

    def __init__(self, device: str):
        self.index = _device_index(device)

    def __enter__(self):
        cuda = _cuda()
        if not cuda.is_available():
            raise ValueError(f"device 'cuda:{self.index}': numba sees no CUDA GPU here")
        self._ctx = cuda.gpus[self.index]
        self._ctx.__enter__()
        return cuda

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def _kernels():
    """The compiled kernels (:mod:`tiledsm.match._cuda_kernels`, imported
    at the first call: importing numba.cuda and compiling are paid by GPU
    runs only)."""
    from tiledsm.match import _cuda_kernels as k

    return k.sample_kernel, k.zncc_kernel, k.fill_kernel, k.path_kernel, k.winner_kernel


def _launch(n: int) -> tuple[int, int]:
    """Blocks and threads of a 1-D launch over ``n`` items."""
    threads = _SIM_THREADS if _simulated() else _THREADS
    return max(1, (n + threads - 1) // threads), threads


#: (kernel, context) pairs launched once: their module is loaded there
_LOADED: set = set()
_LOADING = threading.Lock()


def _run(kernel, grid: tuple[int, int], *args) -> None:
    """Launch ``kernel[grid](*args)``. A kernel's first launch in a CUDA
    context loads its module there, which numba-cuda does not guard against
    threads: sixteen dask threads starting their first task together failed
    with "key already in dictionary: <CUlibrary ...>" (an H100, kernels
    from the disk cache). First launches are therefore taken one at a
    time."""
    key = (kernel, 0 if _simulated() else id(_cuda().current_context()))
    if key in _LOADED:
        kernel[grid](*args)
        return
    with _LOADING:
        kernel[grid](*args)
        _LOADED.add(key)


@dataclass
class DeviceVolume:
    """A cost volume left on the GPU by :func:`cost_volume`.

    Attributes
    ----------
    data : numba.cuda.cudadrv.devicearray.DeviceNDArray
        ``(ny, nx, nd)`` float32 costs (the CPU kernel's volume).
    device : str
        The device it lives on.
    """

    data: object
    device: str

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

    def __array__(self, dtype=None, copy=None):
        with _Selected(self.device):
            host = self.data.copy_to_host()
        return host if dtype is None else host.astype(dtype)


def cost_volume(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None, eps: float = 1e-6, device: str = "cuda",
) -> DeviceVolume:
    """The SGVLL cost volume of a block on ``device``: the arguments and
    values of :func:`tiledsm.match.sweep.cost_volume`, left on the GPU
    (:class:`DeviceVolume`; ``numpy.asarray`` copies it to the host)."""
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(np.max(nvalid)))
    base = np.ascontiguousarray(base, np.int64)
    nvalid = np.ascontiguousarray(nvalid, np.int64)
    lo, hi, ns = sample_plan(base, nvalid, half, details)
    pairs, pw = view_pairs(nv, pair_w)
    sample_k, zncc_k, fill_k, _, _ = _kernels()
    with _Selected(device) as cuda:
        vol = cuda.device_array((ny, nx, nd), np.float32)
        d_nvalid = cuda.to_device(nvalid)
        _run(fill_k, _launch(ny * nx * nd), d_nvalid, vol)
        if ns <= 0:
            return DeviceVolume(vol, device)
        # the views' windows in one padded stack (their shapes alongside)
        shapes = np.array([im.shape for im in imgs], np.int64)
        stack = np.full((nv, int(shapes[:, 0].max()), int(shapes[:, 1].max())), np.nan, np.float32)
        for v, im in enumerate(imgs):
            stack[v, : im.shape[0], : im.shape[1]] = im
        d_lo = cuda.to_device(lo)
        samp = cuda.device_array((nv, ny, nx, ns), np.float32)
        _run(sample_k, _launch(ny * nx * ns),
            cuda.to_device(stack), cuda.to_device(shapes), cuda.to_device(np.ascontiguousarray(lat_r, np.float64)),
            cuda.to_device(np.ascontiguousarray(lat_c, np.float64)), int(stride), int(k0), float(dh),
            cuda.to_device(np.ascontiguousarray(href, np.float64)), float(step), int(origin[0]), int(origin[1]),
            int(nodes0[0]), int(nodes0[1]), cuda.to_device(np.asarray(win_r, np.float64)),
            cuda.to_device(np.asarray(win_c, np.float64)), bool(cubic), d_lo, cuda.to_device(hi), samp,
        )
        _run(zncc_k, _launch(ny * nx * nd),
            samp, d_lo, cuda.to_device(base), d_nvalid, int(half),
            cuda.to_device(np.array([p[0] for p in pairs], np.int64)),
            cuda.to_device(np.array([p[1] for p in pairs], np.int64)), cuda.to_device(pw), float(eps), vol,
        )
        del samp
    return DeviceVolume(vol, device)


def _block_threads(nd: int) -> int:
    """Threads of a path block: a power of two (the minimum's tree), one
    warp at least, at most 1024 (wider cells loop over their candidates);
    4 in the simulator (so that its tests take that loop too)."""
    if _simulated():
        return 4
    t = 32
    while t < nd and t < 1024:
        t *= 2
    return t


def _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, device):
    """``(S, cost, nvalid)`` on the device after the 8 paths."""
    from tiledsm.match.sgm import checked_volume

    on_device = isinstance(cost, DeviceVolume)
    if on_device:
        # the checks of checked_volume without a host copy of the volume
        ny, nx, nd = cost.shape
        if P2 < P1 or P1 < 0:
            raise ValueError(f"aggregate: need 0 <= P1 <= P2, got P1={P1}, P2={P2}")
        b = np.zeros((ny, nx), np.int64) if base is None else np.ascontiguousarray(base, np.int64)
        n = np.full((ny, nx), nd, np.int64) if nvalid is None else np.clip(np.asarray(nvalid, np.int64), 0, nd)
        if b.shape != (ny, nx) or n.shape != (ny, nx):
            raise ValueError(f"aggregate: base and nvalid must be {(ny, nx)}, got {b.shape} and {n.shape}")
        host = None
    else:
        host, b, n = checked_volume(cost, P1, P2, base, nvalid)
        ny, nx, nd = host.shape
    shape = (ny, nx, nd)
    _, _, _, path_k, _ = _kernels()
    cuda = _cuda()
    d_cost = cost.data if on_device else cuda.to_device(host)
    d_base = cuda.to_device(b)
    d_n = cuda.to_device(n)
    S = cuda.to_device(np.zeros(shape, np.float32))
    threads = _block_threads(nd)
    gi0, gj0, period = int(origin[0]), int(origin[1]), int(restart_period)
    p1, p2, inv = np.float32(P1), np.float32(P2), np.float32(invalid_cost)
    for di, dj in DIRECTIONS:
        lines = ny if di == 0 else nx if dj == 0 else nx + ny - 1
        buf = cuda.device_array((lines, 2, nd), np.float32)
        # the in-row paths keep their minimum in float64, the others in float32
        _run(path_k, (lines, threads), d_cost, d_base, d_n, p1, p2, inv, di, dj, gi0, gj0, period, di != 0, S, buf)
    return S, d_cost, d_n


def aggregate(
    cost, P1: float, P2: float, base: np.ndarray | None = None, nvalid: np.ndarray | None = None,
    guide: np.ndarray | None = None, p2_gamma: float = 10.0, invalid_cost: float = 1.0,
    origin: tuple[int, int] = (0, 0), restart_period: int = 0, device: str = "cuda",
) -> np.ndarray:
    """Semi-global aggregation over 8 paths on the GPU: the arguments and
    result of :func:`tiledsm.match.sgm.aggregate` (no ``guide``), as a
    numpy array; ``cost`` a numpy volume or a :class:`DeviceVolume`."""
    if guide is not None:
        raise ValueError("the cuda kernel aggregates without a guide image")
    with _Selected(device):
        S, _, d_n = _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, device)
        S = S.copy_to_host()
        # absent candidates: +inf, as the CPU passes sum them
        S[np.arange(S.shape[2]) >= d_n.copy_to_host()[..., None]] = np.inf
        return S


def best(
    cost, P1: float, P2: float, base: np.ndarray | None = None, nvalid: np.ndarray | None = None,
    invalid_cost: float = 1.0, origin: tuple[int, int] = (0, 0), restart_period: int = 0, device: str = "cuda",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`aggregate` then the winners on the GPU: the arguments and
    results of :func:`tiledsm.match.sgm.aggregate_best` (``index, smin,
    ratio, cbest``), only these four ``(ny, nx)`` arrays copied back."""
    _, _, _, _, winner_k = _kernels()
    with _Selected(device) as cuda:
        S, d_cost, d_n = _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, device)
        ny, nx, _ = S.shape
        out = [cuda.device_array((ny, nx), np.float32) for _ in range(4)]
        _run(winner_k, _launch(ny * nx), S, d_cost, d_n, *out)
        return tuple(o.copy_to_host() for o in out)
