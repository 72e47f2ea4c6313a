"""benchmarks/_measure.py: wall time and process-tree memory of a command.

Oracle: child processes that each hold a known number of touched bytes (numpy arrays filled with
ones), so the tree's resident memory is known to within the interpreter's own footprint.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks._measure import measure  # noqa: E402

MIB = 2**20

# two worker processes, each holding 150 MiB of touched memory for 1 s
_TWO_WORKERS = textwrap.dedent(
    """
    import multiprocessing as mp, time
    import numpy as np
    def hold(_):
        a = np.ones(150 * 2**20 // 8)
        time.sleep(1.0)
        return float(a[0])
    if __name__ == "__main__":
        with mp.get_context("spawn").Pool(2) as pool:
            print(pool.map(hold, [0, 1]))
    """
)


def test_tree_memory_sums_the_workers(tmp_path):
    script = tmp_path / "two_workers.py"  # a file: spawned workers re-import it (not possible with -c)
    script.write_text(_TWO_WORKERS)
    m = measure([sys.executable, script], log=tmp_path / "log", interval=0.1, timeout=60)
    assert m.ok, (tmp_path / "log").read_text()
    # both 150 MiB arrays are resident at once, in two different processes
    assert m.max_processes >= 3
    assert 150 <= m.peak_single_rss_mib < 150 + 120
    assert m.peak_rss_mib >= 300
    assert m.peak_rss_mib < 300 + 3 * 120  # plus three interpreters with numpy
    if m.peak_pss_mib is not None:
        assert 300 <= m.peak_pss_mib <= m.peak_rss_mib + 1e-6
    assert m.wall_s >= 1.0
    assert m.cpu_s > 0


def test_exit_status_is_reported_not_raised():
    m = measure([sys.executable, "-c", "import sys; sys.exit(3)"])
    assert m.returncode == 3 and not m.ok and not m.timed_out


def test_timeout_kills_the_whole_tree():
    code = "import subprocess, sys; subprocess.run([sys.executable, '-c', 'import time; time.sleep(60)'])"
    m = measure([sys.executable, "-c", code], timeout=1.0, interval=0.1)
    assert m.timed_out and not m.ok
    assert m.wall_s < 10


def test_missing_executable_raises(tmp_path):
    with pytest.raises(FileNotFoundError):
        measure([tmp_path / "no-such-tool"])


_FORKSERVER_BURN = textwrap.dedent(
    """
    import multiprocessing as mp, time
    def burn(_):
        t = time.process_time()
        while time.process_time() - t < 1.0:
            pass
        return 1
    if __name__ == "__main__":
        pool = mp.get_context("forkserver").Pool(2)
        print(pool.map(burn, [0, 1]))
        pool.close()
        pool.join()
    """
)


def test_cpu_of_forkserver_workers_is_counted(tmp_path):
    # the forkserver (parent of the workers) is orphaned at exit, so getrusage never sees the
    # workers' 2 CPU seconds; the sampled tree CPU time does (CARS runs its pool like this)
    script = tmp_path / "burn.py"
    script.write_text(_FORKSERVER_BURN)
    m = measure([sys.executable, script], interval=0.1, timeout=60)
    assert m.ok
    assert m.cpu_s_reaped < 1.0
    assert 1.7 <= m.cpu_s_sampled <= 2.0 + 1.5  # + interpreter start-ups
    assert m.cpu_s == m.cpu_s_sampled
