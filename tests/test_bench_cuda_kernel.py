"""benchmarks/cuda_kernel.py as the GPU session types it, on the CPU.

A session lent a GPU has minutes of device time: the capture
(``--capture``, any machine) must have run beforehand and its calls must
replay. Oracle: the plain sweep (``reference`` kernel), which the compiled
kernel equals bit for bit; so every replayed call of both captured tasks
agrees to the last cell. (The CUDA kernels themselves are checked against
the CPU kernel in the simulator: ``tests/match/test_cuda_kernel.py``; a
captured task is too large for it.)
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "cuda_kernel.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=600)


def test_capture_then_replay_both_tasks(tmp_path):
    calls = tmp_path / "calls"
    cap = _run("--capture", str(calls), "--size", "512", "--chunk", "64", "--levels", "2")
    assert cap.returncode == 0, cap.stderr[-2000:]
    saved = sorted(p.name for p in calls.glob("*.npz"))
    assert saved == ["coarsest_0.npz", "level0_0.npz"]
    # the coarsest task sweeps the whole range (every cell the same
    # candidates); the level-0 task a band around the coarser heights
    coarsest, level0 = (np.load(calls / name)["nvalid"] for name in saved)
    assert coarsest.min() == coarsest.max()
    assert np.median(level0) < coarsest.min()

    out = tmp_path / "cuda_kernel.json"
    rep = _run("--tasks", str(calls), "--kernels", "fast", "reference", "--repeat", "1", "--json", str(out))
    assert rep.returncode == 0, rep.stderr[-2000:]
    rows = json.loads(out.read_text())["rows"]
    assert [(r["call"], r["kernel"]) for r in rows] == [
        ("coarsest_0", "fast"), ("coarsest_0", "reference"), ("level0_0", "fast"), ("level0_0", "reference")]
    for r in rows:
        href = np.load(calls / f"{r['call']}.npz")["href"]
        assert r["cells"] == href.size
        assert r["total_s"] > 0
    for r in rows[1::2]:
        assert r["agreement"] == {"valid_differs": 0.0, "off_1mm": 0.0, "max_dh_m": 0.0, "cbest_max_diff": 0.0}


def test_replay_without_captured_calls_says_so(tmp_path):
    rep = _run("--tasks", str(tmp_path), "--kernels", "fast")
    assert rep.returncode == 2
    assert str(tmp_path) in rep.stderr and "--capture" in rep.stderr
    assert "Traceback" not in rep.stderr
