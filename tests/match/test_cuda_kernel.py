"""The CUDA matching kernel (``kernel="cuda"``) against the compiled CPU one
(``kernel="fast"``).

Without a GPU the kernels run in numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``, set before numba starts, hence a child
process): every launch, block and thread of the real kernels, the threads
as Python threads. There the arithmetic is the CPU kernel's in the same
types and order, so the volumes, aggregated costs, winners and heights
must be equal bit for bit. On a GPU the kernels round every product on
its own (no fused multiply-add), and ``benchmarks/cuda_kernel.py``
measured the same equality there (``benchmarks/results/cuda_kernel.json``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tiledsm.match.sgvll import SGVLLParams

HERE = Path(__file__).resolve().parent

#: run in the simulator: prints one JSON line of comparisons
SIMULATED = textwrap.dedent(
    """
    import json
    import numpy as np
    from tiledsm.match import cuda_kernel
    from tiledsm.match.sgm import aggregate, aggregate_best
    from tiledsm.match.sgvll import SGVLLParams, match_block
    from match_synthetic import CRS, band_with_holes, make_scene

    out = {}
    # a ragged volume: invalid costs, label shifts (some beyond the
    # candidates), absent candidates, gaps, restart lines, a grid origin
    rng = np.random.default_rng(3)
    ny, nx, nd = 9, 8, 6
    vol = (rng.random((ny, nx, nd)) * 2).astype(np.float32)
    vol[rng.random(vol.shape) < 0.05] = np.nan
    base = rng.integers(-3, 4, (ny, nx))
    base[4] += 20
    nvalid = rng.integers(1, nd + 1, (ny, nx))
    nvalid[2, 3] = nvalid[6, 1] = 0
    for name, kw in (("plain", {}), ("restarts", {"origin": (5, 70), "restart_period": 4})):
        args = dict(base=base, nvalid=nvalid, invalid_cost=1.0, **kw)
        S0 = aggregate(vol, 0.3, 2.0, fast=True, **args)
        S1 = cuda_kernel.aggregate(vol, 0.3, 2.0, **args)
        w0 = aggregate_best(vol, 0.3, 2.0, **args)
        w1 = cuda_kernel.best(vol, 0.3, 2.0, **args)
        out[name] = {"S_equal": bool(np.array_equal(S0, S1)), "finite": float(np.isfinite(S0).mean()),
                     "winners_equal": [bool(np.array_equal(a, b, equal_nan=True)) for a, b in zip(w0, w1)]}
    # blocks of a synthetic scene: bands around the truth, some cells not searched
    for name, tilts, interp, rows, cols in (("2 views cubic", (0.4, -0.4), "cubic", slice(30, 42), slice(40, 51)),
                                            ("3 views linear", (0.4, 0.0, -0.4), "linear", slice(30, 39), slice(40, 49))):
        sc = make_scene(tilts=tilts, seed=2)
        gx, gy, truth, lo, hi, kw = band_with_holes(sc, rows, cols, (slice(3, 5), slice(4, 6)))
        res = {}
        for kernel in ("fast", "cuda"):
            p = SGVLLParams(kernel=kernel, interpolation=interp, speckle_size=0,
                            **({"device": "cuda"} if kernel == "cuda" else {}))
            d = {}
            h, c = match_block(sc.images, sc.rpcs, None, gx, gy, CRS, lo, hi, p, details=d, **kw)
            res[kernel] = (h, c, d["n_samples"])
        (h0, c0, n0), (h1, c1, n1) = res["fast"], res["cuda"]
        out[name] = {"heights_equal": bool(np.array_equal(h0, h1, equal_nan=True)),
                     "confidence_equal": bool(np.array_equal(c0, c1, equal_nan=True)),
                     "samples_equal": n0 == n1, "valid": float(np.isfinite(h0).mean()),
                     "median_error_m": float(np.nanmedian(np.abs(h0 - truth)))}
    print(json.dumps(out))
    """
)


@pytest.mark.slow
def test_cuda_kernel_in_the_simulator_gives_the_cpu_kernels_results_bit_for_bit():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1",
           "PYTHONPATH": os.pathsep.join(p for p in (str(HERE), os.environ.get("PYTHONPATH", "")) if p)}
    run = subprocess.run([sys.executable, "-c", SIMULATED], env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-4000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    for name in ("plain", "restarts"):
        assert out[name]["S_equal"] and all(out[name]["winners_equal"]), (name, out[name])
        # +inf where a cell lacks the candidate: not all finite, not none
        assert 0.4 < out[name]["finite"] < 0.9
    for name in ("2 views cubic", "3 views linear"):
        r = out[name]
        assert r["heights_equal"] and r["confidence_equal"] and r["samples_equal"], (name, r)
        # a real match, not two empty maps: measured 0.36 / 0.33 of the
        # cells (windows and edges of a small block), median error 0.05 m
        assert r["valid"] > 0.25 and r["median_error_m"] < 0.1, (name, r)


def test_cuda_kernel_names_a_device_it_cannot_use():
    with pytest.raises(ValueError, match="'gpu7'.*cuda, cuda:N"):
        SGVLLParams(kernel="cuda", device="gpu7")
    from numba import cuda

    if not cuda.is_available():
        with pytest.raises(ValueError, match="'cuda'.*numba sees no CUDA GPU"):
            SGVLLParams(kernel="cuda", device="cuda")
    with pytest.raises(ValueError, match="runs on the CPU only"):
        SGVLLParams(kernel="fast", device="cuda")


def test_dsm_plans_a_cuda_run_in_the_simulator(tmp_path):
    """``tiledsm dsm --device cuda --dry-run`` under numba's CUDA simulator,
    which reports no GPU memory (infinite): the plan leaves the GPU budget
    out instead of failing on it (it ended in an OverflowError traceback)."""
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    scene = tmp_path / "scene"
    cli = [sys.executable, "-m", "tiledsm"]
    made = subprocess.run([*cli, "synth", str(scene), "--size", "128", "--seed", "0"], env=env, capture_output=True,
                          text=True, timeout=300)
    assert made.returncode == 0, made.stderr[-3000:]

    def dry_run(device):
        return subprocess.run([*cli, "dsm", str(scene / "view_0.tif"), str(scene / "view_1.tif"), "--like",
                               str(scene / "truth_dsm.tif"), "--out", str(tmp_path / "out"), "--device", device,
                               "--workers", "2", "--scheduler", "threads", "--dry-run"],
                              env=env, capture_output=True, text=True, timeout=300)

    # every GPU numba sees (the simulator's one) is as good as naming it
    for device in ("cuda", "cuda:all"):
        run = dry_run(device)
        assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
        assert "Traceback" not in run.stderr and "per worker" in run.stdout
    assert not (tmp_path / "out").exists()  # a dry run writes nothing
    # two GPUs named where there is one: a line naming the option
    run = dry_run("cuda:0,1")
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert "--device" in run.stderr and "'cuda:0,1': only 1 CUDA device(s) here" in run.stderr, run.stderr[-2000:]


class _FakeCuda:
    """numba.cuda as far as the device names need it: ``gpus`` GPUs."""

    def __init__(self, gpus: int):
        self.gpus = list(range(gpus))

    def is_available(self) -> bool:
        return bool(self.gpus)


def test_device_names_one_or_several_gpus(monkeypatch):
    from tiledsm.match import cuda_kernel as ck

    monkeypatch.setattr(ck, "_cuda", lambda: _FakeCuda(4))
    assert ck.device_indices("cuda") == (0,)
    assert ck.device_indices("cuda:2") == (2,)
    assert ck.device_indices("cuda:3,1") == (3, 1)
    assert ck.device_indices("cuda:all") == (0, 1, 2, 3)
    ck.check_device("cuda:0,3")
    with pytest.raises(ValueError, match=r"'cuda:1,4'.*only 4 CUDA device\(s\) here"):
        ck.check_device("cuda:1,4")
    with pytest.raises(ValueError, match="'cuda:1,1'.*named twice"):
        ck.check_device("cuda:1,1")
    for bad in ("cuda:", "cuda:1,", "cuda:x", "gpu:0"):
        with pytest.raises(ValueError, match="cuda, cuda:N, cuda:N,M"):
            ck.device_indices(bad)
    monkeypatch.setattr(ck, "_cuda", lambda: _FakeCuda(0))
    with pytest.raises(ValueError, match="'cuda:all'.*numba sees no CUDA GPU"):
        ck.device_indices("cuda:all")


def test_threads_take_the_gpus_in_turn_and_keep_theirs(monkeypatch):
    """Eight threads on four GPUs: two on each, every thread always on
    the same one (its volume stays where it was made); a process whose
    dask worker is named 1 starts its round one GPU further. (Each thread
    returns what it saw: an assertion inside a thread would not fail the
    test.)"""
    import itertools
    import threading

    from tiledsm.match import cuda_kernel as ck

    monkeypatch.setattr(ck, "_cuda", lambda: _FakeCuda(4))

    def held_by_threads(offset: int, threads: int = 8) -> list[tuple[int, ...]]:
        monkeypatch.setattr(ck, "_worker_offset", lambda: offset)
        monkeypatch.setattr(ck, "_NEXT_THREAD", itertools.count())
        seen: list[tuple[int, ...]] = []
        start = threading.Barrier(threads)

        def work():
            start.wait()
            seen.append(tuple(ck.thread_device("cuda:all") for _ in range(6)) + (ck.thread_device("cuda:2"),))

        pool = [threading.Thread(target=work) for _ in range(threads)]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
        assert len(seen) == threads
        return seen

    for offset in (0, 1):
        seen = held_by_threads(offset)
        assert all(len(set(s[:6])) == 1 for s in seen)  # a thread keeps its GPU
        assert all(s[6] == 2 for s in seen)  # one GPU named: that one
        assert sorted(s[0] for s in seen) == [0, 0, 1, 1, 2, 2, 3, 3]
    # the process's first thread: its worker's number decides where it starts
    assert held_by_threads(1, threads=1)[0][0] == 1
    assert held_by_threads(0, threads=1)[0][0] == 0


def test_each_worker_of_a_cluster_starts_its_round_at_its_number():
    """A local cluster (on 127.0.0.1) names its workers 0, 1: a task on
    each gets its worker's number, so the first threads of the two take
    different GPUs; outside a worker the round starts at 0."""
    from distributed import Client, LocalCluster

    from tiledsm.match import cuda_kernel as ck

    assert ck._worker_offset() == 0
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp", host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        got = {name: client.submit(ck._worker_offset, workers=[addr], pure=False).result()
               for addr, name in ((a, w.name) for a, w in cluster.scheduler.workers.items())}
    assert got == {0: 0, 1: 1}
