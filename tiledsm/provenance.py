"""Provenance of a run folder: what a stored result was computed from, and
who is writing it.

A run folder (``--out DIR``) holds a resumable store of a DSM. A rerun may
resume it only if everything that determines the result is unchanged. This
module provides the pieces, all small and free of I/O beyond the files they
name:

- :func:`input_identity` -- path, size, mtime and a *sampled* content hash of
  an input file (cheap even for 10 GB images).
- :func:`fingerprint` -- a JSON-serialisable dict of named parts (inputs,
  cameras, grid, parameters...) plus the tiledsm version and the fingerprint
  schema version (:data:`FORMAT`). Values are normalised so that a
  fingerprint written to JSON and read back compares equal to a freshly
  built one.
- :func:`differences` / :func:`check_resume` -- what changed between a
  stored and a current fingerprint, as dotted key paths; ``check_resume``
  raises :class:`~tiledsm.errors.FingerprintMismatchError` with a one-line
  message.
- :func:`write_fingerprint` / :func:`read_fingerprint` -- atomic JSON file.

The lock that keeps two runs out of one folder is
:class:`tiledsm.io.lock.OutputLock`.

Resume compares input **path, size and content hash**, not modification
times: ``mtime_ns`` is kept in the identity for the log, but listed in
:data:`IGNORED_KEYS`, so touching or copying an input does not block a
resume.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import hashlib
import json
import logging
import math
import os
import stat
import sys
import uuid
from importlib import metadata
from pathlib import Path, PurePath
from typing import Any, Mapping

from tiledsm.errors import FingerprintMismatchError, InputFileError

__all__ = [
    "code_hash",
    "FORMAT",
    "IGNORED_KEYS",
    "SAMPLE_BYTES",
    "SAMPLE_COUNT",
    "input_identity",
    "fingerprint",
    "differences",
    "write_fingerprint",
    "read_fingerprint",
    "check_resume",
]

log = logging.getLogger("tiledsm")

#: schema version of :func:`fingerprint` dicts; bump when their layout or the
#: content-hash sampling changes (an old store then no longer resumes)
FORMAT = 1
#: size of each sampled block of :func:`input_identity`'s content hash
SAMPLE_BYTES = 1 << 20
#: number of evenly spaced interior blocks sampled besides the first and last
SAMPLE_COUNT = 16
#: keys that :func:`differences` (hence :func:`check_resume`) ignores at any
#: depth: an input's modification time and path are logged but do not block
#: resume (a run folder copied or inputs moved keep their content hash)
IGNORED_KEYS: frozenset[str] = frozenset({"mtime_ns", "path"})

#: how many differences :func:`check_resume` lists before "and N more"
_MAX_LISTED = 5
#: longest rendering of a value in a difference before it is abbreviated
_MAX_VALUE = 60
#: lists of scalars up to this length are shown whole in a difference
_MAX_LIST_SHOWN = 8


# --------------------------------------------------------------------------- inputs
def _sample_offsets(size: int) -> list[int]:
    """Byte offsets of the blocks hashed for a file of ``size`` bytes: the
    first block, :data:`SAMPLE_COUNT` evenly spaced interior blocks and the
    last block. A file no larger than all of them together is read whole."""
    n = SAMPLE_COUNT + 2
    if size <= n * SAMPLE_BYTES:
        return list(range(0, size, SAMPLE_BYTES)) or [0]
    span = size - SAMPLE_BYTES
    return [span * i // (n - 1) for i in range(n)]


def input_identity(path: str | os.PathLike) -> dict[str, Any]:
    """Identity of an input file: where it is, how big, and a content hash.

    The content hash is a **sampled** hash, not a hash of the whole file:
    ``blake2b`` (16-byte digest) of the file size followed by the first
    :data:`SAMPLE_BYTES` (1 MiB), :data:`SAMPLE_COUNT` (16) blocks of 1 MiB
    at evenly spaced offsets in between, and the last 1 MiB (each block
    preceded by its offset). Files of at most 18 MiB are thereby hashed
    whole. This reads at most 18 MiB, so identifying a 10 GB image costs a
    few milliseconds instead of a minute, and it catches what actually
    happens to inputs (another file under the same name, a re-export, a
    truncated copy, a changed header). It does *not* detect a change
    confined to bytes between the samples of a file larger than 18 MiB with
    its size unchanged.

    Parameters
    ----------
    path : path-like
        The input file.

    Returns
    -------
    dict
        ``path`` (absolute, symlinks resolved), ``size`` (bytes),
        ``mtime_ns`` (informative only, see :data:`IGNORED_KEYS`) and
        ``content_hash`` (hex digest).

    Raises
    ------
    InputFileError
        The file is missing, not a regular file or unreadable.
    """
    p = Path(path)
    try:
        resolved = p.resolve(strict=True)
        with open(resolved, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise IsADirectoryError(21, "not a regular file")
            h = hashlib.blake2b(digest_size=16)
            h.update(st.st_size.to_bytes(8, "little"))
            for off in _sample_offsets(st.st_size):
                f.seek(off)
                h.update(off.to_bytes(8, "little"))
                h.update(f.read(SAMPLE_BYTES))
    except OSError as e:
        raise InputFileError(f"{p}: cannot read input file ({e.strerror or e})") from e
    return {
        "path": str(resolved),
        "size": st.st_size,
        "mtime_ns": st.st_mtime_ns,
        "content_hash": h.hexdigest(),
    }


# --------------------------------------------------------------------------- fingerprint
def _package_version() -> str:
    """Installed version of tiledsm (distribution metadata, else ``__version__``)."""
    try:
        return metadata.version("tiledsm")
    except metadata.PackageNotFoundError:
        import tiledsm

        return str(getattr(tiledsm, "__version__", "unknown"))


_CODE_HASH: str | None = None


def code_hash() -> str:
    """blake2b of every ``.py`` source file of the installed ``tiledsm``
    package (relative path + content, sorted): any change to the code that
    computed a stored result (an editable install, a new release) makes its
    fingerprint differ, so nothing is resumed across code versions.
    Computed once per process."""
    global _CODE_HASH
    if _CODE_HASH is None:
        import tiledsm

        root = Path(tiledsm.__file__).resolve().parent
        h = hashlib.blake2b(digest_size=16)
        for f in sorted(root.rglob("*.py")):
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
        _CODE_HASH = h.hexdigest()
    return _CODE_HASH


def _normalise(value: Any, where: str) -> Any:
    """JSON-exact form of ``value``: what ``json.loads(json.dumps(v))`` returns.

    Tuples/lists/sets -> lists (sets sorted), mappings -> dicts with str keys,
    numpy scalars/arrays -> Python numbers/lists, paths -> str, enums -> their
    value, dataclasses -> dicts of their fields that take part in equality
    (fields declared ``compare=False``, e.g. a camera's ``source``, are
    left out). Finite floats are kept as they are (JSON writes ``repr``,
    which round-trips exactly); non-finite floats become the strings
    ``"NaN"``, ``"Infinity"``, ``"-Infinity"`` (``NaN != NaN`` would
    otherwise never compare equal).
    """
    np = sys.modules.get("numpy")  # a numpy object implies numpy is imported
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, enum.Enum):
        return _normalise(value.value, where)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return float(value)
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if np is not None and isinstance(value, np.generic):
        return _normalise(value.item(), where)
    if np is not None and isinstance(value, np.ndarray):
        return _normalise(value.tolist(), where)
    if isinstance(value, PurePath):
        return str(value)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: _normalise(getattr(value, f.name), f"{where}.{f.name}")
            for f in dataclasses.fields(value)
            if f.compare
        }
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for k, v in value.items():
            if isinstance(k, enum.Enum):
                k = k.value
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"{where}: key {k!r} is not a str or int (fingerprint keys must be)")
            key = str(k)
            if key in out:
                raise ValueError(f"{where}: keys {key!r} collide once converted to str")
            out[key] = _normalise(v, f"{where}.{key}")
        return out
    if isinstance(value, (list, tuple)):
        return [_normalise(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, (set, frozenset)):
        items = [_normalise(v, f"{where}{{}}") for v in value]
        return sorted(items, key=lambda v: json.dumps(v, sort_keys=True))
    raise TypeError(f"{where}: cannot put a {type(value).__name__} into a fingerprint")


def fingerprint(**parts: Any) -> dict[str, Any]:
    """Fingerprint of a result: everything that determines it, as plain JSON.

    Parameters
    ----------
    **parts
        Named parts, e.g. ``inputs=[input_identity(p) for p in images]``,
        ``rpcs=[rpc, ...]`` (dataclasses are expanded), ``grid={...}``,
        ``height_range=(lo, hi)``, ``params={...}``. Values are normalised
        (see :func:`_normalise`): tuples -> lists, numpy -> Python numbers and
        lists, paths -> str, dataclasses -> dicts, nested.

    Returns
    -------
    dict
        The parts, plus ``version`` (installed tiledsm version), ``code``
        (:func:`code_hash`) and ``format`` (:data:`FORMAT`). ``json.loads(json.dumps(fp)) == fp``.

    Raises
    ------
    ValueError
        A part is named ``version`` or ``format`` (reserved).
    TypeError
        A value cannot be represented in JSON (the message names its key path).
    """
    reserved = {"version", "code", "format"} & parts.keys()
    if reserved:
        raise ValueError(f"fingerprint: part name(s) {sorted(reserved)} are reserved")
    fp = {name: _normalise(value, name) for name, value in parts.items()}
    fp["version"] = _package_version()
    fp["code"] = code_hash()
    fp["format"] = FORMAT
    return fp


# --------------------------------------------------------------------------- differences
def _short(value: Any) -> str:
    """One-line rendering of a JSON value, abbreviated in the middle."""
    text = value if isinstance(value, str) and value and value.isprintable() else json.dumps(
        value, sort_keys=True, ensure_ascii=False
    )
    text = text.replace("\n", " ").replace("\r", " ")
    if len(text) > _MAX_VALUE:
        half = (_MAX_VALUE - 1) // 2
        text = text[:half] + "…" + text[-half:]
    return text


def _short_path(path: Any) -> str:
    text = str(path)
    return text if len(text) <= _MAX_VALUE else "…" + text[-(_MAX_VALUE - 1) :]


def _same(a: Any, b: Any) -> bool:
    """Exact equality of JSON leaves (``True`` is not ``1``; ``1 == 1.0``)."""
    return isinstance(a, bool) == isinstance(b, bool) and type(a) is not dict and a == b


def _is_identity(d: Any) -> bool:
    return isinstance(d, dict) and "path" in d and "content_hash" in d


def _diff(old: Any, new: Any, where: str, ignore: frozenset[str], out: list[str]) -> None:
    if isinstance(old, dict) and isinstance(new, dict):
        file = new.get("path") if _is_identity(old) and _is_identity(new) else None
        for key in sorted(set(old) | set(new)):
            if key in ignore:
                continue
            sub = f"{where}.{key}" if where else key
            if key not in new:
                out.append(f"{sub} removed (was {_short(old[key])})")
            elif key not in old:
                out.append(f"{sub} added ({_short(new[key])})")
            elif file is not None and key == "content_hash":
                if old[key] != new[key]:
                    out.append(f"{where} content changed: {_short_path(file)}")
            elif file is not None and key != "path":
                n = len(out)
                _diff(old[key], new[key], sub, ignore, out)
                out[n:] = [f"{d} ({_short_path(file)})" for d in out[n:]]
            else:
                _diff(old[key], new[key], sub, ignore, out)
        return
    if isinstance(old, list) and isinstance(new, list):
        scalar = all(not isinstance(v, (dict, list)) for v in old + new)
        if scalar:
            if len(old) != len(new):
                if max(len(old), len(new)) <= _MAX_LIST_SHOWN:
                    out.append(f"{where}: {_short(old)} -> {_short(new)}")
                else:
                    out.append(f"{where}: {len(old)} values -> {len(new)} values")
                return
            changed = [i for i, (a, b) in enumerate(zip(old, new)) if not _same(a, b)]
            if not changed:
                return
            if len(old) <= _MAX_LIST_SHOWN:
                out.append(f"{where}: {_short(old)} -> {_short(new)}")
            else:
                i = changed[0]
                out.append(
                    f"{where}: {len(changed)} of {len(old)} values differ "
                    f"(first [{i}]: {_short(old[i])} -> {_short(new[i])})"
                )
            return
        for i, (a, b) in enumerate(zip(old, new)):
            _diff(a, b, f"{where}[{i}]", ignore, out)
        for i in range(len(new), len(old)):
            label = f" ({_short_path(old[i]['path'])})" if _is_identity(old[i]) else ""
            out.append(f"{where}[{i}] removed{label}")
        for i in range(len(old), len(new)):
            label = f" ({_short_path(new[i]['path'])})" if _is_identity(new[i]) else ""
            out.append(f"{where}[{i}] added{label}")
        return
    if not _same(old, new):
        out.append(f"{where}: {_short(old)} -> {_short(new)}")


def differences(
    old: Mapping[str, Any], new: Mapping[str, Any], ignore: frozenset[str] = IGNORED_KEYS
) -> list[str]:
    """What changed from fingerprint ``old`` to ``new``, for humans.

    Parameters
    ----------
    old, new : dict
        Fingerprints (any JSON-like dicts; both are normalised first).
    ignore : frozenset of str
        Keys skipped at any depth; by default :data:`IGNORED_KEYS`
        (modification times).

    Returns
    -------
    list of str
        One entry per change, keys sorted, as dotted key paths with list
        indices, e.g. ``"params.match.window: 5 -> 7"``,
        ``"inputs[1] content changed: /data/right.tif"``,
        ``"inputs[1].size: 10 -> 12 (/data/right.tif)"``,
        ``"grid.crs added (EPSG:32631)"``, ``"params.x removed (was 3)"``.
        Changes inside an input identity (a dict with ``path`` and
        ``content_hash``) name the file. Floats compare exactly. Empty when
        nothing (outside ``ignore``) changed.
    """
    out: list[str] = []
    _diff(_normalise(old, "old"), _normalise(new, "new"), "", frozenset(ignore), out)
    return out


def check_resume(stored: Mapping[str, Any] | None, current: Mapping[str, Any], what: str) -> None:
    """Refuse to resume a result computed from something else.

    Parameters
    ----------
    stored : dict or None
        Fingerprint found in the output folder (None: nothing stored, so
        nothing to contradict).
    current : dict
        Fingerprint of this run.
    what : str
        The output folder or store, named at the start of the message.

    Raises
    ------
    FingerprintMismatchError
        The fingerprints differ (:func:`differences`); the one-line message
        lists up to five differences, then "and N more", and says to rerun
        with ``--overwrite`` or use another ``--out``.
    """
    if stored is None:
        return
    diffs = differences(stored, current)
    if not diffs:
        return
    listed = "; ".join(diffs[:_MAX_LISTED])
    if len(diffs) > _MAX_LISTED:
        listed += f"; and {len(diffs) - _MAX_LISTED} more"
    msg = (
        f"{what}: the result stored here (finished or partial) was computed with other inputs or "
        f"parameters ({listed}); rerun with --overwrite to recompute, or use another --out"
    )
    raise FingerprintMismatchError(" ".join(msg.splitlines()))


# --------------------------------------------------------------------------- files
def write_fingerprint(path: str | os.PathLike, fp: Mapping[str, Any]) -> None:
    """Write a fingerprint as JSON, atomically.

    The JSON (sorted keys, strict: no NaN tokens) is written and fsynced to a
    hidden temporary sibling, then ``os.replace``-d onto ``path``: ``path``
    is always either the old or the new complete file. Parent folders are
    created.

    Parameters
    ----------
    path : path-like
        Destination file, e.g. ``DIR/fingerprint.json``.
    fp : dict
        Fingerprint (normalised again, so any :func:`fingerprint` input works).
    """
    final = Path(path)
    text = json.dumps(_normalise(fp, "fingerprint"), sort_keys=True, indent=2, allow_nan=False) + "\n"
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{uuid.uuid4().hex[:10]}")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def read_fingerprint(path: str | os.PathLike) -> dict[str, Any] | None:
    """Read a fingerprint written by :func:`write_fingerprint`.

    Returns
    -------
    dict or None
        The fingerprint, or None when ``path`` does not exist.

    Raises
    ------
    InputFileError
        The file exists but is unreadable, not JSON or not a JSON object.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as e:
        raise InputFileError(f"{p}: cannot read the run fingerprint ({e})") from e
    try:
        fp = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputFileError(f"{p}: corrupt run fingerprint, not JSON ({e}); delete it or rerun with --overwrite") from e
    if not isinstance(fp, dict):
        raise InputFileError(f"{p}: corrupt run fingerprint, expected a JSON object; delete it or rerun with --overwrite")
    return fp
