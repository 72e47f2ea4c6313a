"""Whether this user can write into a folder, and where numba caches when
the installation is read-only. Imported by :mod:`tiledsm` itself: no heavy
import here."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Mapping, MutableMapping

__all__ = ["unwritable", "direct_numba_cache", "numba_user_cache"]


def unwritable(folder: str | os.PathLike) -> tuple[Path, str] | None:
    """``(the folder at fault, reason)`` when this user cannot create files
    in ``folder`` -- or, where it does not exist yet, in the nearest folder
    above it that does (where it would be created): a read-only file
    system, or no write permission; ``None`` when it can. Nothing is
    created."""
    existing = Path(folder).expanduser().absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if os.statvfs(existing).f_flag & os.ST_RDONLY:
        return existing, "read-only file system"
    if not os.access(existing, os.W_OK | os.X_OK):
        return existing, "permission denied: this user may not create files in it"
    return None


def numba_user_cache(environ: Mapping[str, str]) -> Path | None:
    """numba's user-wide cache folder (``$XDG_CACHE_HOME/numba``, else
    ``~/.cache/numba``), as :mod:`numba.misc.appdirs` finds it on Linux."""
    base = environ.get("XDG_CACHE_HOME")
    if base:
        return Path(base) / "numba"
    home = environ.get("HOME")
    return Path(home) / ".cache" / "numba" if home else None


def direct_numba_cache(package: str | os.PathLike, environ: MutableMapping[str, str] = os.environ) -> str | None:
    """Set ``NUMBA_CACHE_DIR`` in ``environ`` to a folder of this user in the
    temporary folder when numba could cache the compiled kernels of
    ``package`` (``cache=True``) neither beside their sources (its
    ``__pycache__``: a read-only installation) nor in the user's cache
    (no writable home); returns the folder set, or ``None`` (numba's own
    places work, or the user chose one).

    Without it, the first kernel compiled ends the command with numba's
    ``RuntimeError: cannot cache function ...: no locator available``.
    Must run before numba is imported: numba reads the variable then.
    """
    if environ.get("NUMBA_CACHE_DIR"):
        return None
    user = numba_user_cache(environ)
    if unwritable(Path(package) / "__pycache__") is None or (user is not None and unwritable(user) is None):
        return None
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    folder = str(Path(tempfile.gettempdir()) / f"tiledsm-numba-cache-{uid}")
    environ["NUMBA_CACHE_DIR"] = folder
    return folder
