"""Atomic writes: a product appears under its final name only when complete."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import uuid
from pathlib import Path
from glob import escape as glob_escape
from typing import Iterator

from tiledsm.errors import TiledsmError


# --------------------------------------------------------------------------- atomic
def remove_path(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def withdraw(folder: str | os.PathLike, names) -> list[str]:
    """Remove the products ``names`` of ``folder`` that exist, in the given
    order (a report first, so that it never describes products that are
    half gone), before a run writes them anew: an interrupted run then
    leaves no report of an earlier run beside new products. Returns the
    names removed."""
    folder = Path(folder)
    removed = [n for n in names if (folder / n).exists()]
    for n in removed:
        remove_path(folder / n)
    return removed


def _tmp_sibling(final: Path, tag: str) -> Path:
    return final.with_name(f".{final.name}.{tag}-{uuid.uuid4().hex[:10]}{final.suffix}")


#: names of :func:`atomic_path`'s temporaries (``.dsm.tif.tmp-0123456789.tif``) and of what writers put
#: beside them (the COG's ``….src.tif`` and GDAL's ``….ovr.tmp``, ``….aux.xml``), and of a product
#: renamed aside by :func:`commit_path` (``.dsm.zarr.old-…``)
TEMPORARY = re.compile(r"^\..+\.(tmp|old)-[0-9a-f]{10}")
#: folders :func:`sweep_temporaries` does not enter: stores of many chunk files, which hold no temporary
_NOT_ENTERED = (".zarr", ".zarr.partial")


def sweep_temporaries(folder: str | os.PathLike, depth: int = 3) -> list[Path]:
    """Remove the temporaries that a killed run left in ``folder`` and its
    subfolders (down to ``depth``): a killed process never reaches
    :func:`atomic_path`'s clean-up, and a COG export leaves an
    uncompressed copy of the whole grid (gigabytes on a whole scene).
    Call it only while holding the folder's lock
    (:class:`tiledsm.io.lock.OutputLock`): then no live run is writing
    them. Returns the paths removed."""
    removed = []
    for root, dirs, files in os.walk(folder):
        level = len(Path(root).relative_to(folder).parts)
        for name in [*files, *dirs]:
            if TEMPORARY.match(name):
                remove_path(Path(root) / name)
                removed.append(Path(root) / name)
        dirs[:] = [d for d in dirs if level < depth and not TEMPORARY.match(d) and not d.endswith(_NOT_ENTERED)]
    return removed


def commit_path(tmp: Path, final: Path) -> None:
    """Move ``tmp`` onto ``final``. Files: one atomic ``os.replace``.
    Directories: the old one is first renamed aside, so ``final`` is at every
    instant either the complete old or the complete new product (or absent
    for the instant between the two renames)."""
    if final.exists() and (final.is_dir() or tmp.is_dir()):
        old = _tmp_sibling(final, "old")
        os.rename(final, old)
        os.rename(tmp, final)
        remove_path(old)
    else:
        os.replace(tmp, final)
    side_tmp, side_final = Path(str(tmp) + ".aux.xml"), Path(str(final) + ".aux.xml")
    if side_tmp.exists():
        os.replace(side_tmp, side_final)
    elif final.is_file():
        with contextlib.suppress(FileNotFoundError):
            side_final.unlink()  # stale GDAL sidecar of a previous product


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Write a file or directory atomically.

    Yields a temporary sibling path (hidden, same suffix, same filesystem);
    write the product there. On normal exit it is renamed onto ``path``
    (replacing an existing product); on any exception it is deleted and the
    exception propagates, leaving ``path`` untouched.

    Parameters
    ----------
    path : path-like
        Final product path (file or directory). Parent folders are created.
    overwrite : bool
        When False and ``path`` exists, raise :class:`TiledsmError` before
        writing anything.

    Examples
    --------
    >>> with atomic_path("out/dsm.tif") as tmp:          # doctest: +SKIP
    ...     write_something(tmp)
    """
    final = Path(path)
    if not overwrite and final.exists():
        raise TiledsmError(f"{final}: already exists (refusing to overwrite)")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_sibling(final, "tmp")
    try:
        yield tmp
        if not tmp.exists():
            raise TiledsmError(f"{final}: the writer produced nothing at its temporary path {tmp}")
        commit_path(tmp, final)
    except BaseException:
        # the temporary and whatever its writer put beside it (a COG's source, GDAL's .ovr.tmp, .aux.xml)
        for p in [tmp, *tmp.parent.glob(glob_escape(tmp.name) + ".*")]:
            remove_path(p)
        raise


