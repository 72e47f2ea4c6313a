"""Run a command as a subprocess; measure its wall time and the peak memory of its process tree.

Shared by the benchmarks (``benchmarks/peers.py``, ``benchmarks/dsm.py``). Multi-process tools
(dask ``LocalCluster`` workers, CARS's multiprocessing pool) spread their memory over many
processes, so the peak RSS of one process (what ``/usr/bin/time -v`` or
``getrusage(RUSAGE_CHILDREN).ru_maxrss`` report) under-states the footprint. Here the whole tree
(the command and all its descendants) is sampled every ``interval`` seconds and the per-sample sums
are maximised.

Memory conventions (all MiB = 2**20 bytes):

- ``peak_rss_mib``: max over samples of the sum of RSS over the tree. Pages shared between
  processes (forked copy-on-write pages, shared libraries) count once per process, so this is an
  upper bound of the physical memory used.
- ``peak_pss_mib``: max over samples of the sum of PSS (proportional set size: shared pages
  divided among their sharers), read from ``/proc/PID/smaps_rollup``; the closest figure to "RAM
  the tree really occupied". Samples where a process's PSS could not be read are skipped;
  ``None`` where the kernel never exposes it.
- ``peak_single_rss_mib``: the largest RSS any one process of the tree reached (sampled), i.e. the
  peak memory per worker.

Peaks shorter than ``interval`` may be missed; processes that detach from the tree (double fork,
re-parenting to init) are not followed.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import resource
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Mapping, Sequence

__all__ = ["Measurement", "measure", "tree_memory", "scheduler_args"]

_MIB = 2.0**20
_PAGE = os.sysconf("SC_PAGE_SIZE")
_TICK = os.sysconf("SC_CLK_TCK")

try:  # psutil is optional: /proc is the fallback (Linux only)
    import psutil
except ImportError:  # pragma: no cover - depends on the environment
    psutil = None


@dataclass(frozen=True)
class Measurement:
    """What :func:`measure` observed for one command.

    Attributes
    ----------
    argv : list of str
        The command.
    returncode : int
        Exit status (negative: killed by that signal; ``-9`` also after a timeout).
    timed_out : bool
        True when the command ran past ``timeout`` and was killed.
    wall_s : float
        Wall-clock seconds from start to exit.
    cpu_s : float
        User + system CPU seconds of the tree: the larger of ``cpu_s_reaped`` and
        ``cpu_s_sampled``.
    cpu_s_reaped : float
        From ``getrusage(RUSAGE_CHILDREN)``: exact, but only for descendants whose parents waited
        for them (a multiprocessing forkserver orphaned at exit takes its workers' time with it).
    sys_s_reaped : float
        The system (kernel) part of ``cpu_s_reaped``: page faults, mapping and unmapping memory, I/O.
    cpu_s_sampled : float
        Sum over every process seen in the tree of its last sampled utime + stime: robust to
        re-parenting, short by at most ``interval`` per process.
    peak_rss_mib, peak_pss_mib, peak_single_rss_mib : float or None
        See the module docstring. ``peak_pss_mib`` is ``None`` without ``smaps_rollup``.
    peak_root_rss_mib, peak_descendant_rss_mib : float
        Peak RSS of the command's own process (e.g. a dask client) and of its largest
        descendant (e.g. one dask worker), MiB.
    max_processes : int
        Largest number of live processes seen in the tree at once.
    samples : int
        Number of memory samples taken.
    interval_s : float
        Sampling period, seconds.
    log : str or None
        File that received the command's stdout and stderr.
    load_before, load_after : float
        1-minute load average of the machine just before and after the run (other users' work
        inflates ``wall_s`` on a shared machine).
    """

    argv: list[str]
    returncode: int
    timed_out: bool
    wall_s: float
    cpu_s: float
    cpu_s_reaped: float
    sys_s_reaped: float
    cpu_s_sampled: float
    peak_rss_mib: float
    peak_pss_mib: float | None
    peak_single_rss_mib: float
    peak_root_rss_mib: float
    peak_descendant_rss_mib: float
    max_processes: int
    samples: int
    interval_s: float
    log: str | None
    load_before: float
    load_after: float

    @property
    def ok(self) -> bool:
        """True when the command exited with status 0."""
        return self.returncode == 0 and not self.timed_out

    def to_dict(self) -> dict:
        """Plain-JSON form."""
        return asdict(self)


def _descendants_proc(root: int) -> list[int]:
    """PIDs of ``root`` and all its descendants, from ``/proc/*/stat`` (no psutil)."""
    parent: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                stat = f.read()
        except OSError:
            continue
        # the command name is in parentheses and may contain spaces: split after the last ')'
        fields = stat[stat.rfind(b")") + 2 :].split()
        parent.setdefault(int(fields[1]), []).append(int(entry))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(parent.get(pid, ()))
    return out


def _tree(root: int) -> list[int]:
    if psutil is not None:
        try:
            proc = psutil.Process(root)
            return [root] + [c.pid for c in proc.children(recursive=True)]
        except psutil.Error:
            return []
    return _descendants_proc(root)


def _sample(pid: int) -> tuple[int, int | None, tuple[int, int], int] | None:
    """One process: (RSS bytes, PSS bytes or None, (pid, start time) key, utime+stime ticks).

    ``None`` if the process is gone.
    """
    try:
        with open(f"/proc/{pid}/statm", "rb") as f:
            rss = int(f.read().split()[1]) * _PAGE
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except (OSError, IndexError, ValueError):
        return None
    fields = stat[stat.rfind(b")") + 2 :].split()  # fields[0] is field 3 (state) of proc(5)
    ticks = int(fields[11]) + int(fields[12])  # utime + stime (fields 14, 15)
    key = (pid, int(fields[19]))  # start time (field 22) tells a reused pid apart
    pss = None
    try:
        with open(f"/proc/{pid}/smaps_rollup", "rb") as f:
            for line in f:
                if line.startswith(b"Pss:"):
                    pss = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    return rss, pss, key, ticks


def tree_memory(
    root: int, cpu_ticks: dict | None = None, split: dict | None = None
) -> tuple[float, float | None, float, int]:
    """One sample of the memory of ``root``'s process tree.

    Parameters
    ----------
    root : int
        PID of the tree's root.
    cpu_ticks : dict, optional
        Updated in place: ``(pid, start time) -> utime + stime`` (clock ticks) of every process
        seen, so that the CPU time of processes that later exit (or get re-parented away) stays
        counted.
    split : dict, optional
        Filled with ``root_rss_mib`` (the command's own process, e.g. a dask client) and
        ``max_descendant_rss_mib`` (its largest descendant, e.g. a worker) of this sample.

    Returns
    -------
    rss_mib : float
        Sum of RSS over the tree, MiB.
    pss_mib : float or None
        Sum of PSS over the tree, MiB (``None`` if any live process lacks ``smaps_rollup``).
    max_single_rss_mib : float
        Largest RSS of one process, MiB.
    n : int
        Number of live processes sampled.
    """
    rss_sum, pss_sum, single, n, pss_ok = 0, 0, 0, 0, True
    root_rss, child_rss = 0, 0
    for pid in _tree(root):
        one = _sample(pid)
        if one is None:
            continue
        rss, pss, key, ticks = one
        if pid == root:
            root_rss = rss
        else:
            child_rss = max(child_rss, rss)
        if cpu_ticks is not None:
            cpu_ticks[key] = ticks
        n += 1
        rss_sum += rss
        single = max(single, rss)
        if pss is None:
            pss_ok = False
        else:
            pss_sum += pss
    if split is not None:
        split.update(root_rss_mib=root_rss / _MIB, max_descendant_rss_mib=child_rss / _MIB)
    return rss_sum / _MIB, (pss_sum / _MIB if pss_ok and n else None), single / _MIB, n


def measure(
    argv: Sequence[str | os.PathLike],
    *,
    cwd: str | os.PathLike | None = None,
    env: Mapping[str, str] | None = None,
    log: str | os.PathLike | None = None,
    interval: float = 0.2,
    timeout: float | None = None,
) -> Measurement:
    """Run ``argv`` to completion and measure it.

    Parameters
    ----------
    argv : sequence of str or path
        The command (no shell).
    cwd : path, optional
        Working directory of the command.
    env : mapping, optional
        Environment of the command (default: this process's).
    log : path, optional
        File for the command's stdout and stderr (merged); default: discarded.
    interval : float
        Memory sampling period, seconds.
    timeout : float, optional
        Seconds after which the whole tree is killed (``timed_out`` is then True).

    Returns
    -------
    Measurement
        A non-zero exit is reported, not raised: check ``Measurement.ok``.

    Raises
    ------
    FileNotFoundError
        When the executable does not exist.
    """
    argv = [os.fspath(a) for a in argv]
    out = open(log, "wb") if log is not None else subprocess.DEVNULL
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_before = os.getloadavg()[0]
    peak_rss, peak_pss, peak_single, max_n, samples = 0.0, None, 0.0, 0, 0
    peak_root, peak_child, split = 0.0, 0.0, {}
    cpu_ticks: dict[tuple[int, int], int] = {}
    timed_out = False
    try:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, cwd=cwd, env=None if env is None else dict(env), stdout=out, stderr=subprocess.STDOUT)
        while True:
            rss, pss, single, n = tree_memory(proc.pid, cpu_ticks, split)
            if n:
                samples += 1
                peak_root = max(peak_root, split["root_rss_mib"])
                peak_child = max(peak_child, split["max_descendant_rss_mib"])
                peak_rss, peak_single, max_n = max(peak_rss, rss), max(peak_single, single), max(max_n, n)
                if pss is not None:  # a sample where some process lacked PSS (e.g. exiting) is skipped
                    peak_pss = max(peak_pss or 0.0, pss)
            try:
                proc.wait(timeout=interval)
                break
            except subprocess.TimeoutExpired:
                pass
            if timeout is not None and time.perf_counter() - t0 > timeout:
                timed_out = True
                _kill_tree(proc.pid)
                proc.wait()
                break
        wall = time.perf_counter() - t0
    finally:
        if log is not None:
            out.close()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_reaped = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    cpu_sampled = sum(cpu_ticks.values()) / _TICK
    return Measurement(
        argv=argv,
        returncode=proc.returncode,
        timed_out=timed_out,
        wall_s=wall,
        cpu_s=max(cpu_reaped, cpu_sampled),
        cpu_s_reaped=cpu_reaped,
        sys_s_reaped=after.ru_stime - before.ru_stime,
        cpu_s_sampled=cpu_sampled,
        peak_rss_mib=peak_rss,
        peak_pss_mib=peak_pss,
        peak_single_rss_mib=peak_single,
        peak_root_rss_mib=peak_root,
        peak_descendant_rss_mib=peak_child,
        max_processes=max_n,
        samples=samples,
        interval_s=interval,
        log=None if log is None else str(Path(log)),
        load_before=load_before,
        load_after=os.getloadavg()[0],
    )


def _kill_tree(root: int) -> None:
    """SIGKILL ``root`` and its descendants (children first)."""
    for pid in reversed(_tree(root)):
        try:
            os.kill(pid, 9)
        except (ProcessLookupError, PermissionError):
            pass


def run_tiledsm(*args: str) -> float:
    """Run ``tiledsm ARGS --no-progress`` as a user does (a subprocess of this
    interpreter); seconds of wall time. Exits with its stderr when it fails."""
    import sys

    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "tiledsm", *args, "--no-progress"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"tiledsm {' '.join(args)} failed:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0



def scheduler_args(scheduler: str, workers: int, run_dir: Path) -> list[str]:
    """Options that make a tiledsm command run on ``scheduler``: ``"cluster"``,
    a local cluster of ``workers`` processes asked for by a cluster file
    written into ``run_dir`` (as a user asks for one); otherwise
    ``--workers W --scheduler NAME`` (e.g. ``threads``)."""
    if scheduler == "cluster":
        spec = Path(run_dir) / f"local_{workers}.yaml"
        spec.write_text(f"kind: local\nworkers: {workers}\n")
        return ["--cluster", str(spec)]
    return ["--workers", str(workers), "--scheduler", scheduler]


def write_result(path: Path, benchmark: str, command: str, rows: list[dict], **extra) -> dict:
    """Write a benchmark's JSON: its name, when, the command, the host (machine, cores, load
    averages), ``extra`` fields and ``rows``; print where. Returns the document."""
    doc = {"benchmark": benchmark, "when": _dt.datetime.now().isoformat(timespec="seconds"), "command": command,
           "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "load_avg": list(os.getloadavg())},
           **extra, "rows": rows}
    Path(path).write_text(json.dumps(doc, indent=1))
    print(f"wrote {path}")
    return doc
