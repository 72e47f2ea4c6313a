"""What the run-contract tests of every command share (tests/*/test_*_contract.py,
tests/test_run_contract.py): the command in a subprocess, as a user runs it,
started and watched until a condition holds (its lock taken, a temporary
written), then SIGKILLed; a second run while the first holds the folder;
a refused run's one error line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest


def tiledsm(*args) -> list[str]:
    return [sys.executable, "-m", "tiledsm", *map(str, args)]


def run(cmd: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}"
    return r


def error_line(r: subprocess.CompletedProcess, command: str) -> str:
    """The one ``tiledsm COMMAND: error:`` line of a refused run (exit 2, no traceback)."""
    assert r.returncode == 2, f"expected exit 2, got {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(f"tiledsm {command}: error:")]
    assert len(lines) == 1, r.stderr[-3000:]
    return lines[0]


def start(cmd: list[str], log: Path, env: dict | None = None) -> subprocess.Popen:
    """``cmd`` in its own process group, output into ``log`` (``env``: added
    to this process's environment)."""
    with open(log, "w") as f:
        return subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True,
                                env=None if env is None else {**os.environ, **env})


def wait_until(p: subprocess.Popen, condition: Callable[[], bool], what: str, log: Path, timeout: float = 180) -> None:
    """Poll ``condition`` every 10 ms while ``p`` runs; fail when ``p`` ends
    first or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while not condition():
        if p.poll() is not None:
            pytest.fail(f"the run ended (rc {p.returncode}) before {what}:\n{log.read_text()[-3000:]}")
        if time.monotonic() > deadline:
            os.killpg(p.pid, signal.SIGKILL)
            pytest.fail(f"not {what} within {timeout} s")
        time.sleep(0.01)


def kill(p: subprocess.Popen) -> None:
    """SIGKILL ``p``'s process group (nothing of it survives to clean up)."""
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)
    p.wait(timeout=30)


def killed_when(cmd: list[str], seen: Callable[[], bool], what: str, log: Path, timeout: float = 180) -> None:
    """Start ``cmd`` and SIGKILL its process group as soon as ``seen()`` (``what``, in messages)."""
    p = start(cmd, log)
    try:
        wait_until(p, seen, what, log, timeout)
    finally:
        kill(p)
    assert p.returncode == -signal.SIGKILL


def temporaries(folder: Path) -> list[str]:
    """Names of the atomic writers' temporaries left in ``folder`` (tree)."""
    return sorted(str(q.relative_to(folder)) for q in folder.rglob(".*") if ".tmp-" in q.name or ".old-" in q.name)


def refused_while_held(first_cmd: list[str], second_cmd: list[str], out: Path, command: str, log: Path) -> str:
    """Start ``first_cmd`` (a run into ``out``); once it holds the folder's
    lock, run ``second_cmd`` into ``out`` too; wait for the first to
    finish. Checks that the second was refused (exit 2, one error line
    naming ``out`` and the other run) while the first still ran, that the
    first then finished (exit 0) and released the lock; returns the line.
    The first waits 20 s once it holds the lock (``HOLD_ENV``): on a loaded
    machine a small run could otherwise finish before the second starts."""
    from tiledsm.io.lock import HOLD_ENV

    first = start(first_cmd, log, {HOLD_ENV: "20"})
    try:
        wait_until(first, lambda: (out / ".tiledsm.lock").exists(), "the lock was taken", log)
        second = run(second_cmd, timeout=60)
        first_alive = first.poll() is None
        first.wait(timeout=300)
    finally:
        kill(first)
    line = error_line(second, command)
    assert first_alive, f"the first run ended before the second was refused ({line})"
    assert "another" in line and str(out) in line, line
    assert first.returncode == 0, log.read_text()[-3000:]
    assert not (out / ".tiledsm.lock").exists()
    return line
