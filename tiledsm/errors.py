"""Exception hierarchy: every error tiledsm raises on purpose derives from
:class:`TiledsmError`, and its message names the file or field at fault and
what was expected."""

from __future__ import annotations

__all__ = [
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
