"""Keep numba's cached kernels in step with the sources they were compiled
from. Imported by :mod:`tiledsm` itself: no heavy import here (no numba).

numba's ``cache=True`` checks a compiled kernel against its own source file
only. A kernel that calls or inlines a function of another module, or reads
one of its constants, keeps running the old code when only that other module
changes: after an upgrade that leaves the kernel's own file unchanged (pip
does not remove the ``.nbi``/``.nbc`` files it did not install), or after a
developer's edit. :func:`purge_stale_kernels` removes the cached kernels of
every module whose source, or the source of a package module it imports
(directly or not), changed since the last run; numba then compiles them
again.

Cost: one ``stat`` per source file on every start (the state file keeps the
sources' sizes and modification times); the sources are read, hashed and
scanned for their imports only when one of those changed.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Mapping

__all__ = ["purge_stale_kernels", "kernel_stamps"]

#: the state file, in the package's own ``__pycache__``
STATE_NAME = "kernel_sources.json"

#: a module's text that marks it as holding cached kernels
_CACHED = "cache=True"


def _sources(package: Path) -> list[Path]:
    out = []
    for folder, subs, names in os.walk(package):
        subs[:] = [s for s in subs if s != "__pycache__"]
        out.extend(Path(folder, n) for n in names if n.endswith(".py"))
    return sorted(out)


def _fingerprint(files: list[Path]) -> list[list]:
    out = []
    for p in files:
        st = os.stat(p)
        out.append([str(p), st.st_mtime_ns, st.st_size])
    return out


def _module_name(package: Path, path: Path) -> str:
    rel = path.relative_to(package.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


_FROM = re.compile(rb"^[ \t]*from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)", re.M)
_IMPORT = re.compile(rb"^[ \t]*import[ \t]+([^\n]*)", re.M)


def _imports(source: bytes, name: str, is_package: bool) -> set[str]:
    """Every module ``name``'s source imports (absolute names), with the
    candidates a ``from X import Y`` names (``X`` and ``X.Y``). Read by
    pattern, not parsed: parsing the modules reached from the kernels
    took 0.4 s, reading their patterns 0.09 s (an import in a string
    counts too: at worst a kernel is compiled again once more often)."""
    found: set[str] = set()
    for m in _IMPORT.finditer(source):
        for part in m.group(1).split(b"#")[0].split(b","):
            words = part.split()
            if words:
                found.add(words[0].decode())
    for m in _FROM.finditer(source):
        mod = m.group(1).decode()
        level = len(mod) - len(mod.lstrip("."))
        if level:
            base = name.split(".") if is_package else name.split(".")[:-1]
            base = base[: len(base) - (level - 1)]
            mod = ".".join(base + ([mod[level:]] if mod[level:] else []))
        found.add(mod)
        names = m.group(2).strip(b"()")
        for line in names.split(b"\n"):
            for part in line.split(b"#")[0].split(b","):
                words = part.split()
                if words:
                    found.add(f"{mod}.{words[0].decode()}")
    return found


def kernel_stamps(package: str | os.PathLike) -> dict[str, str]:
    """For each module of ``package`` that holds cached kernels (its text
    has ``cache=True``), a SHA-256 of its source and of the sources of
    every package module it imports, directly or through others; keyed by
    the module's file path. Only the modules so reached are read."""
    import hashlib  # only on a change: OpenSSL's start costs 5 ms

    package = Path(package).absolute()
    root = package.name
    files = _sources(package)
    names = {_module_name(package, p): p for p in files}
    text: dict[Path, bytes] = {}
    deps: dict[Path, set[Path]] = {}

    def read(p: Path) -> bytes:
        if p not in text:
            text[p] = p.read_bytes()
        return text[p]

    def imported(p: Path) -> set[Path]:
        if p not in deps:
            name = _module_name(package, p)
            # (not the parent packages' __init__, which run first but hand
            # the kernel nothing it does not import itself)
            wanted = _imports(read(p), name, p.name == "__init__.py")
            deps[p] = {names[m] for m in wanted if m.split(".")[0] == root and m in names}
        return deps[p]

    stamps = {}
    for p in files:
        if _CACHED.encode() not in read(p):
            continue
        seen, todo = {p}, [p]
        while todo:
            for q in imported(todo.pop()):
                if q not in seen:
                    seen.add(q)
                    todo.append(q)
        digest = hashlib.sha256()
        for q in sorted(seen):
            digest.update(str(q).encode() + b"\0" + hashlib.sha256(read(q)).digest())
        stamps[str(p)] = digest.hexdigest()
    return stamps


def _cache_folders(source: Path, environ: Mapping[str, str]) -> list[Path]:
    """Where numba may keep ``source``'s kernels: its ``__pycache__``, and
    the folder for it under ``NUMBA_CACHE_DIR`` or the user's cache (named
    as numba names it: the folder's name and the SHA-1 of its path)."""
    import hashlib

    from tiledsm.writable import numba_user_cache

    folder = source.parent
    sub = f"{folder.name}_{hashlib.sha1(str(folder).encode()).hexdigest()}"
    out = [folder / "__pycache__"]
    for base in (environ.get("NUMBA_CACHE_DIR"), numba_user_cache(environ)):
        if base:
            out.append(Path(base) / sub)
    return out


def _remove_kernels(source: Path, environ: Mapping[str, str]) -> None:
    prefix = source.stem + "."
    for folder in _cache_folders(source, environ):
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            if f.name.startswith(prefix) and f.suffix in (".nbi", ".nbc"):
                try:
                    f.unlink()
                except OSError:
                    pass  # another process removed it, or a read-only cache: numba checks its own stamp


def _write_state(path: Path, state: dict) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(state))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)


def _state_path(package: Path, environ: Mapping[str, str]) -> Path | None:
    """The state file: in the package's ``__pycache__``, else (a read-only
    installation) in numba's cache folder for this user, one per
    installation; ``None`` where neither can be written."""
    from tiledsm.writable import numba_user_cache, unwritable

    own = package / "__pycache__"
    if unwritable(own) is None:
        return own / STATE_NAME
    base = environ.get("NUMBA_CACHE_DIR") or numba_user_cache(environ)
    if base and unwritable(base) is None:
        tag = "".join(c if c.isalnum() else "_" for c in str(package))[-100:]
        return Path(base) / "tiledsm-kernel-state" / f"{tag}.json"
    return None


def purge_stale_kernels(package: str | os.PathLike, environ: Mapping[str, str] = os.environ) -> list[str]:
    """Remove the cached kernels of the modules of ``package`` whose stamp
    (:func:`kernel_stamps`) changed since the last call; returns their
    files.

    The state lives in ``package/__pycache__/kernel_sources.json``, or
    where that cannot be written in numba's cache folder for this user
    (:func:`_state_path`); where neither can, the check is left to numba's
    own stamp. The first call on an installation without state removes
    every cached kernel once.
    """
    package = Path(package).absolute()
    state_path = _state_path(package, environ)
    if state_path is None:
        return []
    files = _sources(package)
    fingerprint = _fingerprint(files)
    try:
        state = json.loads(state_path.read_text())
    except (OSError, ValueError):
        state = {}
    if state.get("fingerprint") == fingerprint:
        return []
    stamps = kernel_stamps(package)
    old = state.get("stamps", {})
    stale = sorted(p for p, s in stamps.items() if old.get(p) != s)
    for p in stale:
        _remove_kernels(Path(p), environ)
    _write_state(state_path, {"fingerprint": fingerprint, "stamps": stamps})
    return stale
