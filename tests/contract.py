"""What the run-contract tests of each command share: run a ``tiledsm``
command in a subprocess as users do, wait for a moment of a run (its lock
taken, a temporary written), kill its process group there, or start a
second run while the first holds the folder."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Callable


def run(cmd: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def ok(r: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-2000:]}\n--- stderr\n{r.stderr[-3000:]}"
    return r


def error_line(r: subprocess.CompletedProcess, command: str) -> str:
    """The one ``tiledsm COMMAND: error:`` line of a refused run (exit code 2, no traceback)."""
    assert r.returncode == 2 and "Traceback" not in r.stderr, f"rc {r.returncode}\n{r.stderr[-3000:]}"
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(f"tiledsm {command}: error:")]
    assert len(lines) == 1, r.stderr[-3000:]
    return lines[0]


def _wait_for(seen: Callable[[], bool], process: subprocess.Popen, what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not seen():
        assert process.poll() is None, f"the run ended (rc {process.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.02)


def killed_when(cmd: list[str], seen: Callable[[], bool], what: str, log: Path, timeout: float = 180) -> None:
    """Start ``cmd`` and SIGKILL its process group as soon as ``seen()`` (``what``, in messages)."""
    with open(log, "w") as out:
        p = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            _wait_for(seen, p, what, timeout)
        finally:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL


def refused_while_held(first: list[str], second: list[str], folder: Path, command: str, log: Path) -> str:
    """Start ``first``; once it holds ``folder``'s lock run ``second``, which
    must be refused in one line naming the folder and the other run while
    ``first`` still runs; ``first`` must then complete. Returns the line."""
    with open(log, "w") as out:
        p = subprocess.Popen(first, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            _wait_for(lambda: (folder / ".tiledsm.lock").exists(), p, "the lock", 180)
            r = run(second, timeout=120)
            first_alive = p.poll() is None
            p.wait(timeout=300)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=30)
    line = error_line(r, command)
    assert str(folder) in line and "another" in line, line
    assert first_alive, f"the first run ended before the second was refused ({line})"
    assert p.returncode == 0, log.read_text()[-3000:]
    assert not (folder / ".tiledsm.lock").exists()
    return line
