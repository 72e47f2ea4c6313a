"""The lock of an output folder: two runs never write one folder at once."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shlex
import socket
import sys
from datetime import datetime
from pathlib import Path
from typing import Any, Iterator

from tiledsm.errors import OutputLockedError

try:  # POSIX only; without it takeovers are not serialised (see OutputLock)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "OutputLock"]

log = logging.getLogger("tiledsm")

#: name of the lock file inside an output folder
LOCK_NAME = ".tiledsm.lock"

#: seconds a run waits once it holds the lock, before any work (tests set it
#: so that a second run surely meets the first one still running)
HOLD_ENV = "TILEDSM_TEST_LOCK_HOLD_S"


def _hold_for_tests() -> None:
    import time

    time.sleep(float(os.environ.get(HOLD_ENV) or 0))


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (a zombie counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    except OSError:
        return True  # cannot tell: assume alive
    return True


class OutputLock:
    """Exclusive lock of an output folder: the file ``folder/.tiledsm.lock``.

    The lock file is created with ``O_CREAT | O_EXCL`` and holds JSON
    ``{"pid", "host", "started", "command"}``. When it already exists:

    - held by a live process on this host (``os.kill(pid, 0)`` succeeds or
      is refused) -- including this very process through another
      :class:`OutputLock` -- :class:`~tiledsm.errors.OutputLockedError`;
    - held by a dead process on this host, or unreadable/corrupt -- it is
      stale: a warning is logged on the ``tiledsm`` logger, the file is
      removed and the ``O_EXCL`` creation retried once;
    - held by another host -- respected (its liveness cannot be checked):
      :class:`~tiledsm.errors.OutputLockedError`, saying to delete the lock
      file if that run is known to be dead.

    On POSIX the whole acquisition (and release) runs under an ``flock`` of
    the folder itself, so that two processes taking over the same stale lock
    are serialised: without it both could read the stale lock, and the
    second could delete the lock the first had just created (or read it
    before its JSON was written). The ``flock`` is released by the kernel
    if its holder dies, so it never goes stale. ``O_EXCL`` alone still
    guarantees that at most one creator wins. Local filesystems only.

    :meth:`release` removes the file only if it still names this process.

    Parameters
    ----------
    folder : path-like
        The output folder (created if missing).

    Examples
    --------
    >>> with OutputLock("runs/x"):                   # doctest: +SKIP
    ...     compute_into("runs/x")
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self._held = False

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._held

    def __repr__(self) -> str:
        return f"OutputLock({str(self.folder)!r}, held={self._held})"

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    @contextlib.contextmanager
    def _serialised(self) -> Iterator[None]:
        if fcntl is None:  # pragma: no cover - Windows
            yield
            return
        fd = os.open(self.folder, os.O_RDONLY)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
            except OSError as e:  # e.g. some network filesystems
                log.debug("%s: cannot flock the folder (%s); lock takeover is not serialised", self.folder, e)
            yield
        finally:
            os.close(fd)  # closing drops the flock

    def _create(self) -> None:
        """Create the lock file with ``O_EXCL``; FileExistsError if present."""
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": shlex.join(sys.argv),
        }
        fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        try:
            os.write(fd, (json.dumps(info) + "\n").encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)

    def _read(self) -> dict[str, Any] | None:
        """Holder of the lock file; None if it is corrupt or unreadable.
        FileNotFoundError propagates."""
        try:
            info = json.loads(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return None
        if not isinstance(info, dict):
            return None
        pid, host = info.get("pid"), info.get("host")
        if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0 or not isinstance(host, str):
            return None
        return info

    def check(self) -> None:
        """Refuse now, as :meth:`acquire` would, a folder whose lock a live
        run holds (or a run on another host), without taking it: a missing,
        stale or unreadable lock passes (:meth:`acquire` takes it over), and
        so does a lock held by this very process (its plan ran inside it).

        Raises
        ------
        OutputLockedError
        """
        try:
            info = self._read()
        except FileNotFoundError:
            return
        if info is None:
            return
        if info["host"] == socket.gethostname() and (info["pid"] == os.getpid() or not _pid_alive(info["pid"])):
            return
        self._refuse_or_take_over(info, take_over=True)

    def acquire(self) -> None:
        """Take the lock.

        Raises
        ------
        OutputLockedError
            Another live run (or a run on another host) holds it.
        RuntimeError
            This object already holds it.
        """
        if self._held:
            raise RuntimeError(f"{self.path}: this OutputLock is already held")
        self.folder.mkdir(parents=True, exist_ok=True)
        with self._serialised():
            for attempt in range(2):
                try:
                    self._create()
                    self._held = True
                    self._sweep()
                    _hold_for_tests()
                    return
                except FileExistsError:
                    pass
                try:
                    info = self._read()
                except FileNotFoundError:
                    continue  # released meanwhile: retry the creation
                self._refuse_or_take_over(info, take_over=attempt == 0)
        raise OutputLockedError(
            f"{self.folder}: could not take the lock {self.path} (another tiledsm run took it first)"
        )

    def _sweep(self) -> None:
        """Remove what a killed run left half-written in the folder, now that
        no other run can be writing there (:func:`tiledsm.io.atomic.sweep_temporaries`)."""
        from tiledsm.io.atomic import sweep_temporaries

        removed = sweep_temporaries(self.folder)
        if removed:
            log.warning("%s: removed %d temporaries an interrupted run left: %s", self.folder, len(removed),
                        ", ".join(str(p.relative_to(self.folder)) for p in removed))

    def _refuse_or_take_over(self, info: dict[str, Any] | None, take_over: bool) -> None:
        """Raise if the lock of ``info`` is live (or stale and not
        ``take_over``), else remove the stale file."""
        here = socket.gethostname()
        if info is None:
            if not take_over:
                raise OutputLockedError(f"{self.folder}: could not take the lock {self.path} (it is unreadable)")
            log.warning("%s: taking over an unreadable or corrupt lock file", self.path)
        else:
            who = f"pid {info['pid']} on {info['host']}, started {info.get('started', '?')}"
            if info["host"] != here:
                raise OutputLockedError(
                    f"{self.folder}: another tiledsm run is writing there ({who}; another host, "
                    f"so tiledsm cannot tell whether it is still alive); if that run is known to be "
                    f"dead, delete {self.path} and rerun"
                )
            if _pid_alive(info["pid"]):
                raise OutputLockedError(
                    f"{self.folder}: another tiledsm run is writing there ({who}); wait for it to "
                    f"finish, or use another --out"
                )
            if not take_over:
                raise OutputLockedError(
                    f"{self.folder}: could not take the lock {self.path} (another tiledsm run took it first)"
                )
            log.warning("%s: taking over the stale lock of %s (that process is gone)", self.path, who)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    def release(self) -> None:
        """Give the lock back: remove the lock file if it still names this
        process. Does nothing if this object does not hold the lock."""
        if not self._held:
            return
        self._held = False
        try:
            with self._serialised():
                info = self._read()
                if info is not None and info["pid"] == os.getpid() and info["host"] == socket.gethostname():
                    self.path.unlink()
        except FileNotFoundError:
            pass  # the lock file (or the whole folder) is already gone
