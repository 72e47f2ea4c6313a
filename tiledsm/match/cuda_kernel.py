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

**Several GPUs.** A device naming several (``cuda:0,1``, ``cuda:all``)
hands each matching thread one of them for its life, in turn
(:func:`thread_device`): the threads of one process, or of a cluster's
worker processes, feed every GPU with the same graph.
"""

from __future__ import annotations

import itertools
import re
import sys
import threading
from dataclasses import dataclass, field

import numpy as np

from tiledsm.match.sweep import sample_plan, view_pairs

__all__ = ["DeviceVolume", "aggregate", "best", "check_device", "cost_volume", "device_indices", "memory_info",
           "thread_device"]

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
    run there (not ``cuda``, ``cuda:N``, ``cuda:N,M,...`` or ``cuda:all``;
    no CUDA GPU visible to numba; no such index)."""
    _parse_device(device)
    cuda = _cuda()
    if not cuda.is_available():
        raise _no_gpu(device)
    missing = [i for i in device_indices(device) if i >= len(cuda.gpus)]
    if missing:
        raise ValueError(f"device {device!r}: only {len(cuda.gpus)} CUDA device(s) here "
                         f"(indices 0..{len(cuda.gpus) - 1})")


def memory_info(device: str) -> tuple[int, int] | None:
    """``(free, total)`` bytes of the GPU ``device`` (of several: the
    least free and the least total of any, as every one takes an equal
    share of the tasks); None where they are not known (numba's CUDA
    simulator reports infinite memory)."""
    free = total = float("inf")
    for index in device_indices(device):
        with _Selected(index) as cuda:
            f, t = cuda.current_context().get_memory_info()
        free, total = min(free, f), min(total, t)
    if not (np.isfinite(free) and np.isfinite(total)):
        return None
    return int(free), int(total)


def _parse_device(device: str) -> tuple[int, ...] | None:
    """The indices ``device`` names (``None`` for ``cuda:all``); a
    :class:`ValueError` naming it when it is none of the forms."""
    name, sep, rest = str(device).partition(":")
    if name == "cuda" and not sep:
        return (0,)
    if name == "cuda" and rest == "all":
        return None
    parts = rest.split(",")
    if name != "cuda" or not all(p.isdigit() for p in parts):
        raise ValueError(f"device {device!r}: the 'cuda' kernel runs on cuda, cuda:N, cuda:N,M,... "
                         "or cuda:all devices")
    indices = tuple(int(p) for p in parts)
    if len(set(indices)) != len(indices):
        raise ValueError(f"device {device!r}: a GPU named twice")
    return indices


def device_indices(device: str) -> tuple[int, ...]:
    """The GPUs ``device`` names, as numba's indices: ``cuda`` is GPU 0,
    ``cuda:1`` GPU 1, ``cuda:0,2`` GPUs 0 and 2, ``cuda:all`` every GPU
    numba sees (those of ``CUDA_VISIBLE_DEVICES`` where it is set, as a
    batch system sets it)."""
    indices = _parse_device(device)
    if indices is None:
        cuda = _cuda()
        indices = tuple(range(len(cuda.gpus))) if cuda.is_available() else ()
        if not indices:
            raise _no_gpu(device)
    return indices


def _no_gpu(device: str) -> ValueError:
    return ValueError(f"device {device!r}: numba sees no CUDA GPU here (the 'cuda' kernel needs one)")


#: the GPU each thread matches on, where a device names several
_ASSIGNED = threading.local()
_NEXT_THREAD = itertools.count()


def _worker_offset() -> int:
    """Where this process starts its threads' round of GPUs: the number
    that ends its dask worker's name (a local cluster names its workers
    0, 1, ...; dask-jobqueue ``<job>-<process>``), else 0 (the threaded
    scheduler: one process)."""
    worker = sys.modules.get("distributed")  # a worker process has it; threads need not import it
    try:
        name = str(worker.get_worker().name) if worker is not None else ""
    except ValueError:  # not in a worker
        return 0
    digits = re.search(r"(\d+)$", name)
    return int(digits.group(1)) if digits else 0


def thread_device(device: str) -> int:
    """The GPU index this thread matches on: the one ``device`` names, or,
    where it names several, one of them kept by the thread for its life,
    handed to threads in turn (16 threads on ``cuda:0,1,2,3``: 4 per GPU).

    Each dask thread runs its tasks one after another, so a task's volume
    stays on the GPU its thread holds, between :func:`cost_volume` and
    :func:`best`."""
    indices = device_indices(device)
    if len(indices) == 1:
        return indices[0]
    held = getattr(_ASSIGNED, "held", None)
    if held is None:
        held = _ASSIGNED.held = {}
    if indices not in held:
        held[indices] = indices[(next(_NEXT_THREAD) + _worker_offset()) % len(indices)]
    return held[indices]


class _Selected:
    """Context: the numba CUDA device of index ``index`` made current."""

    def __init__(self, index: int):
        self.index = index

    def __enter__(self):
        cuda = _cuda()
        if not cuda.is_available():
            raise ValueError(f"device 'cuda:{self.index}': numba sees no CUDA GPU here")
        self._ctx = cuda.gpus[self.index]
        self._ctx.__enter__()
        return cuda

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def _on_device(device: str, body):
    """``body(cuda, space)`` with GPU ``device`` current, this thread's
    :class:`_Workspace` on it, and numba's context attached to the thread
    meanwhile (``cuda.require_context``).

    Without the attachment numba-cuda looks the context up afresh for every
    launch, upload and download, under one lock for the whole process: on
    an H100 with sixteen dask threads, 27 % of the matching tasks' stack
    samples stood there (``benchmarks/results/dsm_phases_gpu.json``)."""
    index = thread_device(device)
    with _Selected(index) as cuda:
        space = _workspace(cuda, index)
        return cuda.require_context(body)(cuda, space)


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


def _run(kernel, grid: tuple[int, int], stream, *args) -> None:
    """Launch ``kernel[grid]`` on ``stream``. A kernel's first launch in a
    CUDA context loads its module there, which numba-cuda does not guard
    against threads: sixteen dask threads starting their first task
    together failed with "key already in dictionary: <CUlibrary ...>" (an
    H100, kernels from the disk cache). First launches are therefore taken
    one at a time."""
    key = (kernel, 0 if _simulated() else id(_cuda().current_context()))
    if key in _LOADED:
        kernel[grid[0], grid[1], stream](*args)
        return
    with _LOADING:
        kernel[grid[0], grid[1], stream](*args)
        _LOADED.add(key)


class _Workspace:
    """A thread's device buffers and stream on one GPU, reused by its tasks.

    Each dask thread matches its tasks one after another, so a task can
    take the buffers its predecessor used instead of allocating its own:
    ``cuMemAlloc`` and ``cuMemFree`` synchronise the whole device, and
    with sixteen threads each allocating a dozen arrays per task the GPU
    ran one task at a time. Each thread's work goes to its own stream, so
    the tasks of different threads overlap on the device (uploads,
    kernels and downloads); nothing is queued on the default stream,
    which would order every thread's work behind every other's. A buffer
    grows (by a quarter more than asked, to spare a task of slightly
    larger shape a new allocation) and never shrinks: a thread holds the
    device memory of its largest task (:func:`tiledsm.dsm.memory`
    counts that per task).
    """

    def __init__(self, cuda):
        self.cuda = cuda
        self.stream = cuda.stream()
        self._free: dict[str, object] = {}
        self._taken: dict[str, object] = {}

    def take(self, role: str, shape, dtype):
        """A device array ``shape, dtype`` in the buffer ``role``, out of
        the workspace until :meth:`give` returns it (a buffer never given
        back is left to the garbage collector and the next take of its
        role allocates anew)."""
        shape = tuple(int(n) for n in shape)
        dtype = np.dtype(dtype)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if nbytes == 0:
            return self.cuda.device_array(shape, dtype, stream=self.stream)
        buf = self._free.pop(role, None)
        if buf is None or buf.shape[0] < nbytes:
            buf = self.cuda.device_array(max(nbytes + nbytes // 4, 256), np.uint8, stream=self.stream)
        self._taken[role] = buf
        return buf[:nbytes].view(dtype).reshape(shape)

    def give(self, *roles: str) -> None:
        """Return the buffers last taken for ``roles`` to the workspace."""
        self.restore(self.claim(*roles))

    def claim(self, *roles: str) -> list:
        """The buffers last taken for ``roles``, as ``(role, buffer)``
        pairs the caller holds until it gives them back with :meth:`restore`."""
        return [(role, self._taken.pop(role)) for role in roles if role in self._taken]

    def restore(self, held: list) -> None:
        """Put claimed buffers back (the larger of two for a role)."""
        for role, buf in held:
            old = self._free.get(role)
            if old is None or old.shape[0] < buf.shape[0]:
                self._free[role] = buf

    def upload(self, role: str, host) -> object:
        """``host`` (made contiguous) copied into the buffer ``role`` on
        the stream (the copy from pageable memory is complete when this
        returns, so ``host`` may be dropped)."""
        host = np.ascontiguousarray(host)
        dev = self.take(role, host.shape, host.dtype)
        dev.copy_to_device(host, stream=self.stream)
        return dev


_LOCAL = threading.local()


def _workspace(cuda, index: int) -> _Workspace:
    """This thread's :class:`_Workspace` on GPU ``index`` (made current)."""
    spaces = getattr(_LOCAL, "spaces", None)
    if spaces is None:
        spaces = _LOCAL.spaces = {}
    space = spaces.get(index)
    if space is None:
        space = spaces[index] = _Workspace(cuda)
    return space


@dataclass
class DeviceVolume:
    """A cost volume left on the GPU by :func:`cost_volume`.

    Attributes
    ----------
    data : numba.cuda.cudadrv.devicearray.DeviceNDArray
        ``(ny, nx, nd)`` float32 costs (the CPU kernel's volume), in the
        ``"vol"`` buffer of its thread's workspace until :func:`best`
        gives it back.
    device : str
        The GPU it lives on, ``cuda:N`` (one of those the run names).
    base, nvalid : numpy.ndarray
        The host arrays the volume was made with, and their device copies
        (``d_base``, ``d_nvalid``): :func:`best` reuses these when given
        the same arrays.
    stream : numba.cuda.cudadrv.driver.Stream
        The stream its work was queued on.
    held : list
        Its workspace buffers, given back by :func:`best` (after which
        the volume is gone).
    """

    data: object
    device: str
    base: np.ndarray | None = None
    nvalid: np.ndarray | None = None
    d_base: object = None
    d_nvalid: object = None
    stream: object = None
    held: list = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)

    def __array__(self, dtype=None, copy=None):
        def body(cuda, space):
            host = self.data.copy_to_host(stream=self.stream)
            self.stream.synchronize()
            return host

        host = _on_device(self.device, body)
        return host if dtype is None else host.astype(dtype)


def cost_volume(
    imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0, win_r, win_c, cubic, base, nvalid, half,
    pair_w=None, details: dict | None = None, eps: float = 1e-6, device: str = "cuda",
) -> DeviceVolume:
    """The SGVLL cost volume of a block on ``device``: the arguments and
    values of :func:`tiledsm.match.sweep.cost_volume`, left on the GPU
    (:class:`DeviceVolume`; ``numpy.asarray`` copies it to the host).
    The work is queued on this thread's stream and buffers
    (:class:`_Workspace`)."""
    nv = len(imgs)
    ny, nx = href.shape
    nd = max(1, int(np.max(nvalid)))
    base_h = np.ascontiguousarray(base, np.int64)
    nvalid_h = np.ascontiguousarray(nvalid, np.int64)
    lo, hi, ns = sample_plan(base_h, nvalid_h, half, details)
    pairs, pw = view_pairs(nv, pair_w)
    sample_k, zncc_k, fill_k, _, _ = _kernels()
    # the GPU this thread holds, where ``device`` names several: the volume stays there
    device = f"cuda:{thread_device(device)}"

    def body(cuda, space):
        stream = space.stream
        vol = space.take("vol", (ny, nx, nd), np.float32)
        d_nvalid = space.upload("nvalid", nvalid_h)
        d_base = space.upload("base", base_h)
        _run(fill_k, _launch(ny * nx * nd), stream, d_nvalid, vol)
        out = DeviceVolume(vol, device, base, nvalid, d_base, d_nvalid, stream, space.claim("vol", "nvalid", "base"))
        if ns <= 0:
            return out
        # the views' windows in one padded stack (their shapes alongside)
        shapes = np.array([im.shape for im in imgs], np.int64)
        stack = np.full((nv, int(shapes[:, 0].max()), int(shapes[:, 1].max())), np.nan, np.float32)
        for v, im in enumerate(imgs):
            stack[v, : im.shape[0], : im.shape[1]] = im
        d_lo = space.upload("lo", lo)
        samp = space.take("samples", (nv, ny, nx, ns), np.float32)
        _run(sample_k, _launch(ny * nx * ns), stream,
             space.upload("images", stack), space.upload("shapes", shapes),
             space.upload("lat_r", np.asarray(lat_r, np.float64)), space.upload("lat_c", np.asarray(lat_c, np.float64)),
             int(stride), int(k0), float(dh), space.upload("href", np.asarray(href, np.float64)), float(step),
             int(origin[0]), int(origin[1]), int(nodes0[0]), int(nodes0[1]),
             space.upload("win_r", np.asarray(win_r, np.float64)), space.upload("win_c", np.asarray(win_c, np.float64)),
             bool(cubic), d_lo, space.upload("hi", hi), samp,
        )
        _run(zncc_k, _launch(ny * nx * nd), stream,
             samp, d_lo, d_base, d_nvalid, int(half),
             space.upload("pair_u", np.array([p[0] for p in pairs], np.int64)),
             space.upload("pair_v", np.array([p[1] for p in pairs], np.int64)), space.upload("pair_w", pw),
             float(eps), vol,
        )
        # queued work only reads the scratch buffers: the next take (same
        # stream) is ordered after it
        space.give("samples", "images", "shapes", "lat_r", "lat_c", "href", "win_r", "win_c", "lo", "hi",
                   "pair_u", "pair_v", "pair_w")
        return out

    return _on_device(device, body)


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


def _device_inputs(cost, P1, P2, base, nvalid, space):
    """``(d_cost, d_base, d_nvalid)`` on the device for the paths: a
    :class:`DeviceVolume`'s own (its base and nvalid reused when these are
    the arrays it was made with), or a numpy volume checked by
    :func:`tiledsm.match.sgm.checked_volume` and uploaded."""
    from tiledsm.match.sgm import check_penalties, checked_layout, checked_volume

    if not isinstance(cost, DeviceVolume):
        host, b, n = checked_volume(cost, P1, P2, base, nvalid)
        return space.upload("vol_in", host), space.upload("base_in", b), space.upload("nvalid_in", n)
    if cost.stream is not None and cost.stream is not space.stream:
        cost.stream.synchronize()  # made by another thread
    if base is cost.base and nvalid is cost.nvalid and cost.d_base is not None:
        check_penalties(P1, P2)  # nvalid <= nd holds: nd is its maximum
        return cost.data, cost.d_base, cost.d_nvalid
    b, n = checked_layout(cost.shape, P1, P2, base, nvalid)
    return cost.data, space.upload("base_in", b), space.upload("nvalid_in", n)


def _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, space):
    """``(S, cost, nvalid)`` on the device after the 8 paths, queued on
    ``space``'s stream (``S`` in its ``"S"`` buffer)."""
    _, _, _, path_k, _ = _kernels()
    d_cost, d_base, d_n = _device_inputs(cost, P1, P2, base, nvalid, space)
    ny, nx, nd = d_cost.shape
    S = space.take("S", (ny, nx, nd), np.float32)
    # one buffer of (line, slot, candidate) path costs for every direction:
    # launches on one stream run in order
    buf = space.take("paths", (nx + ny - 1, 2, nd), np.float32)
    threads = _block_threads(nd)
    gi0, gj0, period = int(origin[0]), int(origin[1]), int(restart_period)
    p1, p2, inv = np.float32(P1), np.float32(P2), np.float32(invalid_cost)
    for d, (di, dj) in enumerate(DIRECTIONS):
        lines = ny if di == 0 else nx if dj == 0 else nx + ny - 1
        # the first direction writes S (every candidate of every cell: its
        # lines cover the block), the others add to it
        _run(path_k, (lines, threads), space.stream, d_cost, d_base, d_n, p1, p2, inv, di, dj, gi0, gj0, period,
             d == 0, S, buf)
    space.give("paths", "vol_in")
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

    def body(cuda, space):
        S, _, d_n = _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, space)
        host_S = S.copy_to_host(stream=space.stream)
        n = d_n.copy_to_host(stream=space.stream)
        space.stream.synchronize()
        space.give("S", "base_in", "nvalid_in")
        return host_S, n

    host_S, n = _on_device(_where(cost, device), body)
    # absent candidates: +inf, as the CPU passes sum them
    host_S[np.arange(host_S.shape[2]) >= n[..., None]] = np.inf
    return host_S


def best(
    cost, P1: float, P2: float, base: np.ndarray | None = None, nvalid: np.ndarray | None = None,
    invalid_cost: float = 1.0, origin: tuple[int, int] = (0, 0), restart_period: int = 0, device: str = "cuda",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`aggregate` then the winners on the GPU: the arguments and
    results of :func:`tiledsm.match.sgm.aggregate_best` (``index, smin,
    ratio, cbest``), one ``(4, ny, nx)`` array copied back. A
    :class:`DeviceVolume`'s buffer goes back to its workspace."""
    _, _, _, _, winner_k = _kernels()

    def body(cuda, space):
        S, d_cost, d_n = _aggregated(cost, P1, P2, base, nvalid, invalid_cost, origin, restart_period, space)
        ny, nx, _ = S.shape
        out = space.take("winners", (4, ny, nx), np.float32)
        _run(winner_k, _launch(ny * nx), space.stream, S, d_cost, d_n, out[0], out[1], out[2], out[3])
        host = out.copy_to_host(stream=space.stream)
        space.stream.synchronize()
        space.give("S", "winners", "base_in", "nvalid_in")
        if isinstance(cost, DeviceVolume):
            space.restore(cost.held)
            cost.held = []
        return host

    host = _on_device(_where(cost, device), body)
    return host[0], host[1], host[2], host[3]


def _where(cost, device: str) -> str:
    """The GPU to aggregate on: a :class:`DeviceVolume`'s own, else
    this thread's of ``device``."""
    return cost.device if isinstance(cost, DeviceVolume) else device
