"""Resuming, refusing and locking run folders, through the command line.

Each test runs ``python -m tiledsm dsm`` in a subprocess (the way users run
it: a crash is a real SIGKILL of the process group, a concurrent run a second
process) on one small synthetic scene (384 px) on its truth grid.

``P1`` (chunk 64: 6 x 6 = 36 chunks, 2 pyramid levels, height range from tie
points) is the reference parameter set; a finished ``P1`` folder is made once
(:func:`finished`) and copied where a test needs a finished run.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tiledsm.io import open_product
from tiledsm.synth import make_scene

P1 = ("--chunk", "64", "--levels", "2")
TOTAL = 36  # chunks of P1 on the 384-cell grid
ERROR_PREFIX = "tiledsm dsm: error:"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene"), size=384, gsd=0.5, bh=0.4, seed=3, views=2)


def dsm_cmd(views, like, out: Path, *extra: str, scheduler: str = "synchronous") -> list[str]:
    return [
        sys.executable, "-m", "tiledsm", "dsm", *map(str, views), "--like", str(like), "--out", str(out),
        "--scheduler", scheduler, "--no-progress", *extra,
    ]


def run(cmd: list[str], timeout: float = 240, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        cmd, capture_output=True, text=True, timeout=timeout, env={**os.environ, **env} if env else None
    )


def _ok(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}"


def error_line(r: subprocess.CompletedProcess) -> str:
    """The one error line of a refused run (and no traceback)."""
    assert r.returncode != 0, f"expected a refusal, got rc 0\n{r.stdout[-2000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(ERROR_PREFIX)]
    assert len(lines) == 1, f"expected one '{ERROR_PREFIX}' line in stderr:\n{r.stderr[-3000:]}"
    return lines[0]


def metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def recipe(out: Path) -> dict:
    return yaml.safe_load((out / "recipe.resolved.yaml").read_text())


def store_fingerprint(store: Path) -> dict:
    import zarr

    return json.loads(zarr.open_group(str(store), mode="r").attrs["fingerprint"])


def done_count(partial: Path) -> int | None:
    """Chunks marked done in a partial store (None while it is not there or
    not readable)."""
    import zarr

    try:
        return int(np.asarray(zarr.open_array(store=str(partial), path="_progress/done", mode="r")[...]).sum())
    except Exception:
        return None


def level_done(store: Path) -> np.ndarray:
    """Which blocks of a DSM level's store (:class:`tiledsm.io.BlockFiles`) are written."""
    from tiledsm.io import BlockFiles

    return BlockFiles.open(store).done()


def _chunk_done(blocks: np.ndarray, chunks: tuple[int, ...], i: int, j: int, side: int = 90) -> bool:
    """Whether every store block under matching chunk ``(i, j)`` of a level
    chunked ``chunks`` per axis is done (a merged chunk covers two blocks
    per axis)."""
    r0 = sum(chunks[:i])
    c0 = sum(chunks[:j])
    rows = range(r0 // side, -(-(r0 + chunks[i]) // side))
    cols = range(c0 // side, -(-(c0 + chunks[j]) // side))
    return bool(blocks[np.ix_(list(rows), list(cols))].all())


def chunks_done(store: Path, chunks: tuple[int, ...] | None = None) -> int:
    """Matching chunks (:data:`L0_CHUNKS` by default) whose blocks are all
    done in ``store`` (0 while it is not there or not readable)."""
    chunks = chunks or L0_CHUNKS
    try:
        blocks = level_done(store)
    except Exception:
        return 0
    return sum(_chunk_done(blocks, chunks, i, j) for i in range(len(chunks)) for j in range(len(chunks)))


def zarr_shape(store: Path) -> tuple[int, ...]:
    """Block layout of a resumable store (its ``_progress/done`` array)."""
    import zarr

    return tuple(zarr.open_array(store=str(store), path="_progress/done", mode="r").shape)


def products(out: Path) -> dict[str, bytes]:
    """Bytes of the products a refused run must leave alone."""
    names = ("metrics.json", "recipe.resolved.yaml", "dsm.tif", "dsm.zarr/zarr.json")
    return {n: (out / n).read_bytes() for n in names}


def heights(out: Path) -> tuple[np.ndarray, np.ndarray]:
    ds = open_product(out / "dsm.zarr")
    return ds["height"].values, ds["confidence"].values


@pytest.fixture(scope="module")
def finished(scene, tmp_path_factory) -> Path:
    """A folder with a finished, uninterrupted P1 run."""
    out = tmp_path_factory.mktemp("finished") / "p1"
    _ok(run(dsm_cmd(scene.views, scene.truth_dsm, out, *P1)))
    m = metrics(out)["timings"]["chunks"]
    assert m == {"chunks_total": TOTAL, "chunks_reused": 0, "chunks_computed": TOTAL}
    assert np.isfinite(heights(out)[0]).mean() > 0.8
    return out


def copy_of(finished: Path, tmp_path: Path) -> Path:
    out = tmp_path / "p1"
    shutil.copytree(finished, out)
    return out


# ------------------------------------------------------------------ 4. kill and resume
# Every level is matched into a store in dsm.levels (tiledsm.dsm.stages) and
# the DSM store is written from the finest one, a chunk once its neighbours
# are matched: the kill lands while the finest level is being matched, which
# is where a run spends its time. A 20-cell speckle size (default 150) keeps
# the final filter's halos local, as they are on a real scene.
KILL_RECIPE_SPECKLE = 20
#: the finest level's matching chunks on the 384-cell grid: chunk 64 is
#: raised to the halos' floor of 90 cells, the last one merged (90, 90, 90, 114)
L0_CHUNKS = (90, 90, 90, 114)
#: the coarse level's: 192 cells in 90, the last one merged
L1_CHUNKS = (90, 102)


def kill_recipe(scene, path: Path) -> Path:
    rec = {
        "pipeline": "dsm",
        "name": "killed",
        "input": {"images": [str(v) for v in scene.views]},
        "grid": {"like": str(scene.truth_dsm), "chunk": 64},
        "match": {"levels": 2, "params": {"speckle_size": KILL_RECIPE_SPECKLE}},
        "output": {"cog": False, "quicklook": False},
    }
    path.write_text(yaml.safe_dump(rec))
    return path


def run_cmd(recipe_path: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "tiledsm", "run", str(recipe_path), "--out", str(out),
            "--scheduler", "synchronous", "--no-progress"]


def test_killed_run_resumes_its_finished_chunks(scene, tmp_path):
    """SIGKILL a run once >= 2 chunks of its finest level are matched; the
    same command then matches only the chunks not finished (metrics and
    stdout say how many it reused) and gives exactly the DSM of an
    uninterrupted run; the level stores are gone once the DSM is."""
    rec = kill_recipe(scene, tmp_path / "killed.yaml")
    out = tmp_path / "killed"
    cmd = run_cmd(rec, out)
    partial = out / "dsm.zarr.partial"
    levels = out / "dsm.levels"
    matching = levels / "L0.blocks"
    with open(tmp_path / "first.log", "w") as log:
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + 180
            while True:
                if chunks_done(matching) >= 2:
                    break
                if p.poll() is not None:
                    pytest.fail(f"the run ended (rc {p.returncode}) before 2 chunks were seen matched:\n"
                                + (tmp_path / "first.log").read_text()[-3000:])
                if time.monotonic() > deadline:
                    pytest.fail("no 2 chunks matched within 180 s")
                time.sleep(0.02)
            os.killpg(p.pid, signal.SIGKILL)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    assert p.returncode == -signal.SIGKILL
    # still partial, and nothing claims a finished run (the DSM chunks whose
    # neighbours were matched may be written already)
    d = done_count(partial)
    assert partial.exists() and not (out / "dsm.zarr").exists() and d < TOTAL
    assert not (out / "metrics.json").exists() and not (out / "recipe.resolved.yaml").exists()
    # the level stores stay; the finest one was partly matched (and
    # the coarse level as far as its finer chunks needed it, here all of it)
    k1 = chunks_done(levels / "L1.blocks", L1_CHUNKS)
    assert k1 == len(L1_CHUNKS) ** 2
    k = chunks_done(matching)
    total = len(L0_CHUNKS) ** 2
    assert 2 <= k < total, k
    # the same command again (the dead run's lock file is stale and taken over)
    r = run(cmd)
    _ok(r)
    assert not partial.exists() and (out / "dsm.zarr").exists()
    assert not levels.exists(), "the level stores outlive the finished DSM"
    timings = metrics(out)["timings"]
    assert {n: timings["levels"]["L0"][n] for n in ("chunks_total", "chunks_reused")} == {
        "chunks_total": total, "chunks_reused": k}, timings["levels"]
    assert {n: timings["levels"]["L1"][n] for n in ("chunks_total", "chunks_reused")} == {
        "chunks_total": len(L1_CHUNKS) ** 2, "chunks_reused": k1}
    assert timings["chunks"] == {"chunks_total": TOTAL, "chunks_reused": d, "chunks_computed": TOTAL - d}
    assert f"reused {k} of {total} matched chunks" in r.stdout
    # an uninterrupted run of the same recipe
    ref = tmp_path / "uninterrupted"
    r = run(run_cmd(rec, ref))
    _ok(r)
    assert metrics(ref)["timings"]["chunks"]["chunks_reused"] == 0
    assert metrics(ref)["timings"]["levels"]["L0"]["chunks_reused"] == 0
    # the resumed run counts the candidates of the chunks it reused too
    assert metrics(ref)["timings"]["levels"] == {
        name: {**rep, "chunks_reused": 0} for name, rep in timings["levels"].items()}
    h, c = heights(out)
    h_ref, c_ref = heights(ref)
    assert np.isfinite(h_ref).mean() > 0.8
    np.testing.assert_array_equal(h, h_ref)
    np.testing.assert_array_equal(c, c_ref)
    assert recipe(out) == recipe(ref)


# ------------------------------------------------------------------ 5. changed parameter
def test_changed_parameter_is_refused_until_overwrite(scene, finished, tmp_path):
    """A rerun into a finished folder with another height range stops with
    one line naming the field and --overwrite, leaving the products as they
    were; with --overwrite it recomputes every chunk."""
    out = copy_of(finished, tmp_path)
    before = products(out)
    fp = store_fingerprint(out / "dsm.zarr")
    p2 = (*P1, "--height-range", "295", "365")
    t0 = time.monotonic()
    line = error_line(run(dsm_cmd(scene.views, scene.truth_dsm, out, *p2)))
    assert "height_range" in line and "--overwrite" in line, line
    assert str(out) in line, line
    assert products(out) == before
    assert store_fingerprint(out / "dsm.zarr") == fp
    assert not (out / "dsm.zarr.partial").exists() and not (out / ".tiledsm.lock").exists()
    refused_s = time.monotonic() - t0

    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *p2, "--overwrite"))
    _ok(r)
    chunks = metrics(out)["timings"]["chunks"]
    assert chunks == {"chunks_total": TOTAL, "chunks_reused": 0, "chunks_computed": TOTAL}, chunks
    assert recipe(out)["match"]["height_range"] == [295.0, 365.0]
    assert metrics(out)["report"]["height_range_m"] == [295.0, 365.0]
    assert store_fingerprint(out / "dsm.zarr")["height_range"] == [295.0, 365.0]
    assert refused_s < 60


# ------------------------------------------------------------------ 6. replaced input
def test_replaced_input_is_refused(scene, tmp_path):
    """An input image rewritten in place (a 20 x 20 pixel patch changed,
    same name, RPCs kept) after a finished run: the rerun stops with one
    line naming the file."""
    import rasterio
    from rasterio.windows import Window

    inputs = tmp_path / "inputs"
    inputs.mkdir()
    views = [Path(shutil.copy2(v, inputs / Path(v).name)) for v in scene.views]
    out = tmp_path / "run"
    # one chunk and a given height range: the quickest complete run
    cmd = dsm_cmd(views, scene.truth_dsm, out, "--chunk", "384", "--levels", "2", "--height-range", "295", "365")
    _ok(run(cmd))
    before = products(out)
    with rasterio.open(views[1], "r+") as f:
        w = Window(150, 150, 20, 20)
        patch = f.read(1, window=w)
        f.write((patch // 2 + 7).astype(patch.dtype), 1, window=w)
    with rasterio.open(views[1]) as f:
        assert f.rpcs is not None
    line = error_line(run(cmd))
    assert str(views[1]) in line or views[1].name in line, line
    assert "content changed" in line and "--overwrite" in line, line
    assert str(views[0]) not in line.replace(str(views[1]), ""), f"the unchanged view is named: {line}"
    assert products(out) == before


# ------------------------------------------------------------------ 7. interrupted before the store
def test_failed_run_with_other_parameters_never_passes_off_the_old_dsm(scene, finished, tmp_path):
    """Issue reproduction: a finished P1 folder; P2 (--levels 1) dies before
    computing anything (no scheduler at tcp://127.0.0.1:9); P2 run normally
    then must not hand back P1's DSM as its own: it is refused naming
    ``levels`` (or recomputed). At no point do recipe.resolved.yaml /
    metrics.json claim P2 while the store holds P1."""
    out = copy_of(finished, tmp_path)
    before = products(out)
    p2 = ("--chunk", "64", "--levels", "1")
    r = run(
        dsm_cmd(scene.views, scene.truth_dsm, out, *p2, scheduler="tcp://127.0.0.1:9"),
        DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="3s",
    )
    assert r.returncode != 0, r.stdout[-2000:]
    assert products(out) == before  # recipe still says levels 2, like the store
    assert recipe(out)["match"]["levels"] == 2
    assert store_fingerprint(out / "dsm.zarr")["levels"] == 2
    assert not (out / ".tiledsm.lock").exists()

    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *p2))
    if r.returncode != 0:
        line = error_line(r)
        assert "levels" in line and "--overwrite" in line, line
        assert products(out) == before
    else:  # recomputed: then everything says P2
        assert metrics(out)["timings"]["chunks"]["chunks_reused"] == 0
    assert recipe(out)["match"]["levels"] == store_fingerprint(out / "dsm.zarr")["levels"]


# ------------------------------------------------------------------ 8. concurrent run
def test_concurrent_run_into_the_same_folder_is_refused(scene, finished, tmp_path):
    """While a run holds ``DIR/.tiledsm.lock``, a second run into DIR (other
    height range) stops at once naming the folder; the first completes."""
    out = tmp_path / "busy"
    with open(tmp_path / "first.log", "w") as log:
        first = subprocess.Popen(
            dsm_cmd(scene.views, scene.truth_dsm, out, *P1), stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            deadline = time.monotonic() + 120
            while not (out / ".tiledsm.lock").exists():
                assert first.poll() is None, "the first run ended before taking the lock"
                assert time.monotonic() < deadline, "no lock file within 120 s"
                time.sleep(0.05)
            t0 = time.monotonic()
            second = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P1, "--height-range", "295", "365"), timeout=60)
            elapsed = time.monotonic() - t0
            first_alive = first.poll() is None
            first.wait(timeout=240)
        finally:
            if first.poll() is None:
                os.killpg(first.pid, signal.SIGKILL)
                first.wait(timeout=30)
    line = error_line(second)
    assert first_alive, f"the first run ended before the second was refused ({line})"
    assert "another" in line and str(out) in line, line
    assert elapsed < 15, f"the second run took {elapsed:.1f} s to stop"
    assert first.returncode == 0, (tmp_path / "first.log").read_text()[-3000:]
    assert metrics(out)["timings"]["chunks"]["chunks_computed"] == TOTAL
    np.testing.assert_array_equal(heights(out)[0], heights(finished)[0])
    assert not (out / ".tiledsm.lock").exists()
