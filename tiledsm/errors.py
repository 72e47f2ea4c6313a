"""Exception hierarchy: every error tiledsm raises on purpose derives from
:class:`TiledsmError`, and its message names the file or field at fault and
what was expected."""

from __future__ import annotations

import errno
import os

__all__ = [
    "FILE_FAULTS",
    "file_fault",
    "TiledsmError",
    "InputFileError",
    "UnsupportedFormatError",
    "RPCError",
    "GridError",
    "NoOverlapError",
    "RecipeError",
    "MatchingError",
    "FingerprintMismatchError",
    "OutputLockedError",
    "WorkerMemoryError",
    "InvalidOptionError",
    "RunTooLargeError",
]


class TiledsmError(Exception):
    """Base class of all tiledsm errors."""


class InputFileError(TiledsmError):
    """Raised when an input file is missing, unreadable or corrupt."""


class UnsupportedFormatError(InputFileError):
    """Raised when a file exists but is in no format tiledsm can read."""


class RPCError(TiledsmError):
    """Raised when a camera model is missing, garbled (wrong coefficient
    count, non-finite values) or cannot be inverted."""


class GridError(TiledsmError):
    """Raised when a ground grid is ill-defined (empty bounds, bad
    resolution, unknown CRS) or lies outside what the images see."""


class NoOverlapError(TiledsmError):
    """Raised when images (or DSMs) have no ground in common."""


class RecipeError(TiledsmError):
    """Raised when a recipe is invalid; the message names the field path."""


class MatchingError(TiledsmError):
    """Raised when dense matching cannot proceed (no valid height range,
    no tie points)."""


class FingerprintMismatchError(TiledsmError):
    """Raised when an output folder holds a (finished or partial) result
    computed from other inputs or parameters than the current run's; the
    message lists what changed and says how to recompute."""


class OutputLockedError(TiledsmError):
    """Raised when another tiledsm run holds the lock of an output folder;
    the message names the folder, the holder (pid, host) and its start time."""


class InvalidOptionError(TiledsmError):
    """Raised when an option or recipe field has a value that cannot work
    (``--workers 0``, an SR scale without weights, an odd chunk side); the
    message names the option or field and what is accepted."""


class RunTooLargeError(GridError):
    """Raised when a run would exceed a stated size limit (cells or chunks
    of its grid, :class:`tiledsm.plan.Limits`) before anything is computed;
    the message gives the sizes, the limits and how to lift them
    (``--allow-large``)."""


class WorkerMemoryError(TiledsmError):
    """A worker died again and again running one task: it was stopped at
    its memory limit (the usual cause), or the machine killed it."""


#: errno values of the machine's faults a run can meet on files, not its
#: inputs' or options': a full disk or quota, a read-only or forbidden folder
FILE_FAULTS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG})


def file_fault(exc: BaseException, output: str | os.PathLike | None = None) -> str | None:
    """One line for an :class:`OSError` that is a fault of the machine
    (:data:`FILE_FAULTS`), naming the file it names (else ``output``, the
    run's output) and the system's reason; ``None`` for any other error.

    The error or one it was raised from counts (a task's ``OSError`` comes
    back through dask as is). A write GDAL failed (a ``RasterioIOError``
    without errno, raised from GDAL's own message: a full disk, whose
    reason GDAL prints itself) counts too, and says how much room the disk
    holding ``output`` has.
    """
    chain, e = [], exc
    while e is not None and len(chain) < 10:
        chain.append(e)
        e = e.__cause__ or e.__context__
    for e in chain:
        if isinstance(e, OSError) and e.errno in FILE_FAULTS:
            if e.filename:
                return f"{e.filename}: {e.strerror}"
            return f"{output}: {e.strerror} (writing into it)" if output else f"{e.strerror}"
    root = str(chain[-1])
    if output is not None and type(exc).__name__ == "RasterioIOError" and "writ" in root.lower():
        free = _free_bytes(output)
        room = "" if free is None else f"; {free / 2**20:.3g} MiB free on its disk once its temporaries are removed"
        return f"{output}: cannot write it ({root}){room}"
    return None


def _free_bytes(path: str | os.PathLike) -> int | None:
    """Free bytes on the disk holding ``path`` (or its nearest existing folder)."""
    import shutil
    from pathlib import Path

    p = Path(path).expanduser().resolve()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None
