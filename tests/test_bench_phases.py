"""benchmarks/dsm_phases.py: the stack sampler and what it reports.

Oracle: threads parked for a known time in functions of known names, and
hand-made collapsed stacks whose shares are counted by hand.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.dsm_phases import StackSampler, top_functions, wait_shares  # noqa: E402


def _staged_task(done: threading.Event) -> None:  # named as the DSM stage's task
    _inner_wait(done)


def _inner_wait(done: threading.Event) -> None:
    done.wait(5)


def test_sampler_sees_where_a_thread_waits():
    done = threading.Event()
    worker = threading.Thread(target=_staged_task, args=(done,))
    sampler = StackSampler(200)
    worker.start()
    sampler.start()
    time.sleep(0.4)
    sampler.halt.set()
    sampler.join()
    done.set()
    worker.join()
    inside = {k: v for k, v in sampler.counts.items() if "_staged_task (test_bench_phases.py" in k}
    assert sum(inside.values()) >= 20  # ~80 at 200 Hz; a loaded machine samples fewer
    assert all(k.split(";")[-1].startswith("wait (threading.py") for k in inside)
    top = top_functions(sampler.counts)
    shares = {r["function"]: r["share"] for r in top if "function" in r}
    assert shares["_inner_wait (test_bench_phases.py)"] == 1.0


def test_wait_shares_counts_each_sample_once_first_match():
    stacks = {
        "run (x.py:1);_staged_task (stages.py:2);match (m.py:3);get_or_create_context (devices.py:4)": 5,
        "run (x.py:1);_staged_task (stages.py:2);open_array (synchronous.py:9);sync (sync.py:7)": 3,
        "run (x.py:1);_despeckled_task (stages.py:5);sync (sync.py:7)": 2,
        "run (x.py:1);_staged_task (stages.py:2);kernel (k.py:8)": 10,
        "main (cli.py:1);sync (sync.py:7)": 100,  # outside the tasks: not counted
    }
    w = wait_shares(stacks)
    assert w["samples"] == 20
    assert w["numba-cuda context lookup"] == 0.25
    assert w["zarr: opening an array"] == 0.15
    assert w["zarr: its I/O loop (reads, writes)"] == 0.1
    assert w["numba: the compiler lock"] == 0.0
