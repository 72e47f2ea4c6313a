"""Run-folder provenance: input identities, fingerprints, resume checks, lock."""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import shutil
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from tiledsm.errors import FingerprintMismatchError, InputFileError, OutputLockedError, TiledsmError
from tiledsm.io.lock import LOCK_NAME, OutputLock
from tiledsm.provenance import (
    FORMAT,
    SAMPLE_BYTES,
    _sample_offsets,
    check_resume,
    differences,
    fingerprint,
    input_identity,
    read_fingerprint,
    write_fingerprint,
)

MiB = 1 << 20


def _flip(path: Path, offset: int) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        b = f.read(1)
        f.seek(offset)
        f.write(bytes([b[0] ^ 0xFF]))


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _write_lock(folder: Path, **info) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    path.write_text(json.dumps({"started": "2020-01-01T00:00:00+00:00", "command": "x", **info}))
    return path


# --------------------------------------------------------------------------- input_identity
def test_input_identity_content_size_and_mtime(tmp_path):
    img = tmp_path / "left.tif"
    img.write_bytes(np.random.default_rng(0).bytes(5 * MiB))
    a = input_identity(img)
    assert set(a) == {"path", "size", "mtime_ns", "content_hash"}
    assert a["path"] == str(img.resolve()) and a["size"] == 5 * MiB

    _flip(img, 5 * MiB // 2)  # a middle byte (small files are hashed whole)
    b = input_identity(img)
    assert b["content_hash"] != a["content_hash"] and b["size"] == a["size"]
    _flip(img, 5 * MiB // 2)  # restore
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns - 10**9))
    c = input_identity(img)
    assert c["mtime_ns"] != a["mtime_ns"]
    assert {k: v for k, v in c.items() if k != "mtime_ns"} == {k: v for k, v in a.items() if k != "mtime_ns"}
    assert differences(fingerprint(inputs=[a]), fingerprint(inputs=[c])) == []  # mtime ignored

    copy = tmp_path / "copy.tif"
    shutil.copyfile(img, copy)
    d = input_identity(copy)
    assert (d["size"], d["content_hash"]) == (a["size"], a["content_hash"])

    with open(img, "ab") as f:
        f.write(b"\0")
    e = input_identity(img)
    assert e["size"] == a["size"] + 1 and e["content_hash"] != a["content_hash"]


def test_input_identity_samples_large_files(tmp_path):
    big = tmp_path / "big.tif"
    size = 40 * MiB
    with open(big, "wb") as f:
        f.truncate(size)  # sparse: fast to write and to read
    offsets = _sample_offsets(size)
    assert len(offsets) == 18 and offsets[0] == 0 and offsets[-1] == size - SAMPLE_BYTES
    base = input_identity(big)["content_hash"]

    _flip(big, offsets[8] + 123)  # inside an interior sample: detected
    assert input_identity(big)["content_hash"] != base
    _flip(big, offsets[8] + 123)
    assert input_identity(big)["content_hash"] == base
    gap = offsets[8] + SAMPLE_BYTES + 1000  # between two samples: not read, by design
    assert gap < offsets[9]
    _flip(big, gap)
    assert input_identity(big)["content_hash"] == base


def test_input_identity_missing_or_not_a_file(tmp_path):
    with pytest.raises(InputFileError, match="nope.tif"):
        input_identity(tmp_path / "nope.tif")
    with pytest.raises(InputFileError, match=str(tmp_path)):
        input_identity(tmp_path)


# --------------------------------------------------------------------------- fingerprint
@dataclass(frozen=True)
class _Cam:
    scale: float
    coeffs: np.ndarray
    source: str = field(default="", compare=False)


def test_fingerprint_json_round_trip(tmp_path):
    fp = fingerprint(
        inputs=[{"path": Path("/a/left.tif"), "size": np.int64(3), "content_hash": "ab"}],
        rpcs=[_Cam(np.float32(0.1), np.arange(3) / 3.0, source="x.RPB")],
        grid={"bounds": (0.0, 1.0, 2.0, 3.0), "res": 0.1 + 0.2, 7: "int key"},
        height_range=(np.float64(-12.5), math.inf),
        params={"match": {"window": 5, "nan": float("nan")}, "on": np.bool_(True)},
    )
    assert fp["version"] == metadata.version("tiledsm") and fp["format"] == FORMAT
    assert fp["rpcs"] == [{"scale": float(np.float32(0.1)), "coeffs": [0.0, 1 / 3, 2 / 3]}]  # source left out
    assert fp["grid"]["bounds"] == [0.0, 1.0, 2.0, 3.0] and fp["grid"]["7"] == "int key"
    assert fp["height_range"] == [-12.5, "Infinity"] and fp["params"]["on"] is True
    assert fp["inputs"][0]["path"] == "/a/left.tif" and type(fp["inputs"][0]["size"]) is int
    assert json.loads(json.dumps(fp)) == fp

    write_fingerprint(tmp_path / "run" / "fingerprint.json", fp)
    back = read_fingerprint(tmp_path / "run" / "fingerprint.json")
    assert back == fp and differences(back, fp) == []
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["fingerprint.json"]  # no temp left

    with pytest.raises(ValueError, match="version"):
        fingerprint(version="1")
    with pytest.raises(TypeError, match=r"params\.bad"):
        fingerprint(params={"bad": object()})


def test_write_fingerprint_failure_keeps_old_and_read_errors(tmp_path):
    path = tmp_path / "fp.json"
    assert read_fingerprint(path) is None
    write_fingerprint(path, {"a": 1})
    with pytest.raises(TypeError):
        write_fingerprint(path, {"a": object()})
    assert read_fingerprint(path) == {"a": 1} and len(list(tmp_path.iterdir())) == 1
    path.write_text('{"a": 1')
    with pytest.raises(InputFileError, match="fp.json"):
        read_fingerprint(path)
    path.write_text("[1, 2]")
    with pytest.raises(InputFileError, match="fp.json"):
        read_fingerprint(path)


# --------------------------------------------------------------------------- differences
def _fp(**over):
    parts = dict(
        inputs=[
            {"path": "/a/left.tif", "size": 10, "mtime_ns": 1, "content_hash": "aa"},
            {"path": "/a/right.tif", "size": 10, "mtime_ns": 1, "content_hash": "bb"},
        ],
        params={"levels": 1, "match": {"window": 5, "sigma": 0.1}},
        grid={"bounds": [0.0, 0.0, 1.0, 1.0]},
        rpcs=[{"line_num": [float(i) for i in range(20)]}],
    )
    parts.update(over)
    return fingerprint(**parts)


def test_differences_names_keys_and_files():
    old = _fp()
    assert differences(old, json.loads(json.dumps(old))) == []
    new = _fp(
        inputs=[
            {"path": "/a/left.tif", "size": 10, "mtime_ns": 99, "content_hash": "aa"},
            {"path": "/a/right.tif", "size": 12, "mtime_ns": 1, "content_hash": "cc"},
            {"path": "/a/third.tif", "size": 1, "mtime_ns": 1, "content_hash": "dd"},
        ],
        params={"levels": 1, "match": {"window": 7, "sigma": math.nextafter(0.1, 1.0)}, "new": True},
        grid={"bounds": [0.0, 0.0, 1.0, 2.0]},
        rpcs=[{"line_num": [float(i) for i in range(19)] + [0.5]}],
    )
    assert differences(old, new) == [
        "grid.bounds: [0.0, 0.0, 1.0, 1.0] -> [0.0, 0.0, 1.0, 2.0]",
        "inputs[1] content changed: /a/right.tif",
        "inputs[1].size: 10 -> 12 (/a/right.tif)",
        "inputs[2] added (/a/third.tif)",
        "params.match.sigma: 0.1 -> 0.10000000000000002",
        "params.match.window: 5 -> 7",
        "params.new added (true)",
        "rpcs[0].line_num: 1 of 20 values differ (first [19]: 19.0 -> 0.5)",
    ]
    assert differences(new, old)[-2:] == ["params.new removed (was true)", "rpcs[0].line_num: 1 of 20 values differ (first [19]: 0.5 -> 19.0)"]
    assert differences({"a": 1}, {"a": True}) == ["a: 1 -> true"]
    assert differences({"a": 1}, {"a": 1.0}) == []


def test_check_resume_one_line_message():
    old = _fp()
    check_resume(None, old, "runs/x")
    check_resume(old, _fp(), "runs/x")
    new = _fp(params={"levels": 2, "match": {"window": 5, "sigma": 0.1}})
    with pytest.raises(FingerprintMismatchError) as ei:
        check_resume(old, new, "runs/x")
    msg = str(ei.value)
    assert isinstance(ei.value, TiledsmError) and "\n" not in msg
    assert msg.startswith("runs/x: ") and "(params.levels: 1 -> 2)" in msg
    assert "--overwrite" in msg and "--out" in msg

    many = _fp(params={f"p{i}": i for i in range(8)})
    with pytest.raises(FingerprintMismatchError, match=r"; and 5 more\)") as ei:
        check_resume(old, many, "runs/x")
    assert "\n" not in str(ei.value) and str(ei.value).count(" added (") + str(ei.value).count(" removed (") == 5


# --------------------------------------------------------------------------- lock
def test_lock_basic_and_same_process_refusal(tmp_path):
    folder = tmp_path / "runs" / "x"
    with OutputLock(folder) as lock:
        assert lock.held
        info = json.loads((folder / LOCK_NAME).read_text())
        assert info["pid"] == os.getpid() and info["host"] == socket.gethostname()
        assert set(info) == {"pid", "host", "started", "command"} and "T" in info["started"]
        with pytest.raises(OutputLockedError) as ei:
            OutputLock(folder).acquire()
        msg = str(ei.value)
        assert str(folder) in msg and f"pid {os.getpid()}" in msg and info["started"] in msg
        assert "another tiledsm run is writing there" in msg and "\n" not in msg
    assert not (folder / LOCK_NAME).exists()
    second = OutputLock(folder)
    second.acquire()
    second.release()
    second.release()  # idempotent
    assert not (folder / LOCK_NAME).exists()


def test_lock_release_keeps_a_lock_that_is_not_ours(tmp_path):
    lock = OutputLock(tmp_path)
    lock.acquire()
    other = _write_lock(tmp_path, pid=os.getpid() + 1, host=socket.gethostname())
    lock.release()
    assert other.exists()


def test_lock_stale_and_corrupt_are_taken_over(tmp_path, caplog):
    path = _write_lock(tmp_path, pid=_dead_pid(), host=socket.gethostname())
    with caplog.at_level("WARNING", logger="tiledsm"):
        with OutputLock(tmp_path):
            assert json.loads(path.read_text())["pid"] == os.getpid()
    assert "stale lock" in caplog.text
    path.write_text("{not json")
    with OutputLock(tmp_path):
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert "corrupt" in caplog.text


def test_lock_of_another_host_is_respected(tmp_path):
    path = _write_lock(tmp_path, pid=_dead_pid(), host="elsewhere.example")
    with pytest.raises(OutputLockedError, match="another host") as ei:
        OutputLock(tmp_path).acquire()
    assert "elsewhere.example" in str(ei.value) and f"delete {path}" in str(ei.value)
    assert json.loads(path.read_text())["host"] == "elsewhere.example"


_HOLD = """
import sys, time
from tiledsm.io.lock import OutputLock
OutputLock(sys.argv[1]).acquire()
print("locked", flush=True)
time.sleep(60)
"""


def test_lock_of_live_child_refused_then_taken_over_after_kill(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        assert (tmp_path / LOCK_NAME).exists()
        with pytest.raises(OutputLockedError, match=f"pid {child.pid} on"):
            OutputLock(tmp_path).acquire()
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
        child.stdout.close()
    with OutputLock(tmp_path):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()


def _race(folder, barrier, results, done) -> None:
    barrier.wait()
    try:
        OutputLock(folder).acquire()
        results.put("won")
    except OutputLockedError:
        results.put("lost")
    done.wait(10)  # the winner holds the lock until both have tried


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="needs fork")
def test_lock_racing_takeover_has_one_winner(tmp_path):
    ctx = multiprocessing.get_context("fork")
    dead = _dead_pid()
    for attempt in range(10):
        folder = tmp_path / f"r{attempt}"
        _write_lock(folder, pid=dead, host=socket.gethostname())
        barrier, results, done = ctx.Barrier(2), ctx.Queue(), ctx.Event()
        procs = [ctx.Process(target=_race, args=(str(folder), barrier, results, done)) for _ in range(2)]
        for p in procs:
            p.start()
        outcome = sorted(results.get(timeout=10) for _ in procs)
        done.set()
        for p in procs:
            p.join(10)
        assert outcome == ["lost", "won"], f"attempt {attempt}"
        assert json.loads((folder / LOCK_NAME).read_text())["pid"] in {p.pid for p in procs}
