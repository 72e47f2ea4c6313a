"""The plan phase (:mod:`tiledsm.plan`): refusals in seconds naming the
option, ``--dry-run`` that writes nothing, warnings in ``metrics.json``,
and interrupted runs that never leave products described by another run.

Issue 18's reproductions, one test (or more) each:

1. stale DSM for new parameters -- interrupted before the store exists,
   while it fills, after it is finished (``test_interrupted_*``; the plain
   refusal is in ``tests/test_resume.py``);
2. two runs into one folder -- ``tests/test_resume.py`` (lock), and the
   plan refusing a folder a live run holds (``test_locked_folder_*``);
3. hangs: a huge grid, ``--workers`` < 1 (``test_huge_grid_*``,
   ``test_workers_below_one_*``);
4. relative ``--out`` on an external cluster (``test_relative_out_*``);
5. late validation: reference, bounds, ``--like``, stable mask, SR scale
   (``test_*_missing_the_scene_*``, ``test_sr_scale_without_weights_*``...);
6. messages naming options the command lacks (``test_every_option_*``), and
   a resumed run saying how many chunks it reused.
"""

from __future__ import annotations

import ast
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine

from test_resume import done_count, dsm_cmd, metrics, products, recipe, run, store_fingerprint
from tiledsm.cli import build_parser, main
from tiledsm.synth import make_scene

#: a quick run on the 256-cell scene: 2 x 2 chunks, one level, ~50 candidates
P1 = ("--chunk", "128", "--levels", "1", "--height-range", "300", "350")
P2 = ("--chunk", "128", "--levels", "1", "--height-range", "300", "360")
TOTAL = 4
REFUSED_WITHIN_S = 30  # seconds (interpreter start, imports and tie points on a loaded 2-core machine)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene"), size=256, gsd=0.5, bh=0.4, seed=3, views=2)


@pytest.fixture(scope="module")
def finished(scene, tmp_path_factory) -> Path:
    """A folder with a finished P1 run."""
    out = tmp_path_factory.mktemp("finished") / "p1"
    _ok(run(dsm_cmd(scene.views, scene.truth_dsm, out, *P1)))
    return out


def copy_of(folder: Path, tmp_path: Path) -> Path:
    import shutil

    out = tmp_path / folder.name
    shutil.copytree(folder, out)
    return out


def _ok(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 0, f"rc {r.returncode}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}"


def _help(command: str) -> str:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices[command].format_help()


def assert_options_in_help(command: str, message: str) -> None:
    """Every ``--option`` a message tells the user about exists in the command's ``--help``."""
    missing = [o for o in re.findall(r"(?<![\w-])--[a-z][a-z-]*", message) if o not in _help(command)]
    assert not missing, f"`tiledsm {command}` has no {missing}, yet its message names them: {message}"


def refused(argv: list[str], capsys) -> str:
    """Run ``tiledsm ARGV`` in process; it must exit 2 within
    REFUSED_WITHIN_S with one error line whose options exist; returns it."""
    t0 = time.monotonic()
    rc = main(argv)
    elapsed = time.monotonic() - t0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"tiledsm {argv[0]}: error:")]
    assert rc == 2 and len(lines) == 1, f"rc {rc}, stderr:\n{err}"
    assert elapsed < REFUSED_WITHIN_S, f"refused after {elapsed:.1f} s"
    assert_options_in_help(argv[0], lines[0])
    return lines[0]


def dsm_argv(scene, out: Path, *extra: str) -> list[str]:
    return ["dsm", *map(str, scene.views), "--out", str(out), "--scheduler", "synchronous", "--no-progress", *extra]


def write_raster(path: Path, crs: str, x0: float, y0: float, shape=(32, 32), res: float = 0.5, nan_rows: int = 0) -> Path:
    z = np.full(shape, 320.0, np.float32)
    z[:nan_rows] = np.nan
    with rasterio.open(path, "w", driver="GTiff", width=shape[1], height=shape[0], count=1, dtype="float32",
                       crs=crs, transform=Affine(res, 0, x0, 0, -res, y0), nodata=float("nan")) as ds:
        ds.write(z, 1)
    return path


def write_polygon(path: Path, crs: str, x0: float, y0: float, side: float) -> Path:
    ring = [[x0, y0], [x0 + side, y0], [x0 + side, y0 - side], [x0, y0 - side], [x0, y0]]
    path.write_text(json.dumps({
        "type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": crs}},
        "features": [{"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring]}}],
    }))
    return path


def truth_grid(scene):
    from tiledsm.io.grids import grid_like

    return grid_like(scene.truth_dsm)


# ------------------------------------------------------------------ dry run
def test_dry_run_prints_the_plan_and_writes_nothing(scene, tmp_path, capsys):
    out = tmp_path / "new"
    assert main(dsm_argv(scene, out, "--like", str(scene.truth_dsm), "--reference", str(scene.truth_dsm),
                         *P1, "--dry-run")) == 0
    text = capsys.readouterr().out
    assert not out.exists()
    for key in ("grid", "levels", "tasks", "memory", "reuse", "nothing (no DSM in"):
        assert key in text, text
    assert "256 x 256 cells" in text and "2 x 2 = 4" in text, text
    assert f"--reference: {scene.truth_dsm}" in text and "covers 100% of the grid" in text, text


def test_dry_run_on_a_finished_folder_says_what_is_reused(scene, finished, tmp_path, capsys):
    out = copy_of(finished, tmp_path)
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    assert main(dsm_argv(scene, out, "--like", str(scene.truth_dsm), *P1, "--dry-run")) == 0
    assert f"all {TOTAL} chunks of the finished DSM" in capsys.readouterr().out
    assert main(dsm_argv(scene, out, "--like", str(scene.truth_dsm), *P2, "--overwrite", "--dry-run")) == 0
    assert "--overwrite discards the finished DSM" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before


def test_dry_run_refuses_what_the_run_would_refuse(scene, finished, tmp_path, capsys):
    """Other parameters than the stored DSM's: the dry run stops with the run's own message."""
    out = copy_of(finished, tmp_path)
    line = refused(dsm_argv(scene, out, "--like", str(scene.truth_dsm), *P2, "--dry-run"), capsys)
    assert "height_range" in line and "--overwrite" in line, line


def test_plan_resolves_every_path_to_an_absolute_one(scene, tmp_path, monkeypatch):
    """Issue reproduction 4, in the plan: a relative --out (and inputs) are
    absolute before any worker sees them."""
    from tiledsm.cli.dsm import dsm_recipe
    from tiledsm.pipelines import plan_recipe

    monkeypatch.chdir(scene.out_dir)
    args = build_parser().parse_args(
        ["dsm", "view_0.tif", "view_1.tif", "--out", "rel/out", "--like", "truth_dsm.tif", "--reference",
         "truth_dsm.tif", *P1])
    r = dsm_recipe(args)
    assert all(Path(p).is_absolute() for p in (*r.input.images, r.input.reference, r.grid.like))
    plan = plan_recipe(r, args.out)
    assert plan.out == scene.out_dir.resolve() / "rel" / "out"
    assert all(Path(i.path).is_absolute() for i in plan.inputs)
    assert not (scene.out_dir / "rel").exists()


def test_dry_run_of_sr_compare_and_run(scene, tmp_path, capsys):
    out = tmp_path / "hr"
    assert main(["sr", str(scene.views[0]), str(out), "--model", "bicubic", "--chunk", "128", "--dry-run"]) == 0
    assert "512 x 512 px output (x2) in sr.tif" in capsys.readouterr().out and not out.exists()
    assert main(["compare", str(scene.truth_dsm), str(scene.truth_dsm), "--out", str(tmp_path / "c"), "--dry-run"]) == 0
    assert "OTHER covers 100% of it" in capsys.readouterr().out and not (tmp_path / "c").exists()
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump({"pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
                                    "grid": {"like": str(scene.truth_dsm), "chunk": 128}}))
    assert main(["run", str(path), "--out", str(tmp_path / "r"), "--dry-run"]) == 0
    assert "tasks" in capsys.readouterr().out and not (tmp_path / "r").exists()


@pytest.mark.parametrize("key", ["gcps", "check_points"])
def test_a_recipe_orient_file_that_is_missing_is_refused_by_the_plan(scene, tmp_path, capsys, key):
    """The files of a recipe's ``orient:`` section are inputs: a missing one
    is refused by the plan, naming its field, before the folder exists
    (the DSM plan once checked only the images, and the run failed after
    the orientation had started)."""
    path = tmp_path / "r.yaml"
    present = tmp_path / "present.csv"
    present.write_text("id,image,lon,lat,h,row,col\n")
    orient = {"gcps": str(present), key: str(tmp_path / "missing.csv")}
    path.write_text(yaml.safe_dump({"pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
                                    "orient": orient}))
    out = tmp_path / "r"
    line = refused(["run", str(path), "--out", str(out), "--dry-run"], capsys)
    assert f"orient.{key}" in line and "missing.csv" in line and "no such file" in line, line
    assert not out.exists()


# ------------------------------------------------------------------ 3. hangs
def test_huge_grid_is_refused_in_seconds_unless_allowed(scene, tmp_path, capsys):
    """Issue reproduction 3: --resolution 0.001 on a 128 m scene (a 1.3e5²
    grid) stops at once naming --resolution and --allow-large."""
    out = tmp_path / "huge"
    line = refused(dsm_argv(scene, out, "--resolution", "0.001", "--height-range", "300", "350"), capsys)
    assert "--resolution 0.001" in line and "--allow-large" in line and "chunks" in line, line
    assert not out.exists()


def test_limits_are_stated_and_lifted():
    from tiledsm.errors import RunTooLargeError
    from tiledsm.plan import Limits

    Limits().check(4 * 10**9, 20_000, "x", "y")
    with pytest.raises(RunTooLargeError, match="20,001 chunks"):
        Limits().check(10, 20_001, "x", "y")
    Limits(allow_large=True).check(10**12, 10**7, "x", "y")


@pytest.mark.parametrize("command", ["dsm", "run", "compare", "sr"])
@pytest.mark.parametrize("workers", ["-2", "0"])
def test_workers_below_one_are_refused(scene, tmp_path, capsys, command, workers):
    """Issue reproduction 3: --workers -2 started a cluster without workers and waited forever."""
    argv = {
        "dsm": dsm_argv(scene, tmp_path / "o", *P1),
        "run": ["run", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")],
        "compare": ["compare", str(scene.truth_dsm), str(scene.truth_dsm), "--out", str(tmp_path / "o")],
        "sr": ["sr", str(scene.views[0]), str(tmp_path / "o")],
    }[command]
    argv = [a for a in argv if a != "synchronous" and a != "--scheduler"]
    line = refused(argv + ["--workers", workers], capsys)
    assert f"--workers: must be at least 1 worker, got {workers}" in line, line
    assert not (tmp_path / "o").exists()


def test_locked_folder_is_refused_by_the_plan(scene, tmp_path, capsys):
    """Issue reproduction 2, before anything else: a folder a live process holds."""
    out = tmp_path / "busy"
    out.mkdir()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        import socket

        (out / ".tiledsm.lock").write_text(json.dumps({"pid": other.pid, "host": socket.gethostname(),
                                                       "started": "now"}))
        line = refused(dsm_argv(scene, out, *P1, "--dry-run"), capsys)
    finally:
        other.kill()
        other.wait()
    assert f"pid {other.pid}" in line and str(out) in line, line


# ------------------------------------------------------------------ 5. late validation
def test_missing_reference_is_refused_before_matching(scene, tmp_path, capsys):
    line = refused(dsm_argv(scene, tmp_path / "o", *P1, "--reference", str(tmp_path / "nope.tif")), capsys)
    assert f"{tmp_path / 'nope.tif'}: --reference: no such file" in line
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"not a raster")
    line = refused(dsm_argv(scene, tmp_path / "o", *P1, "--reference", str(garbage)), capsys)
    assert str(garbage) in line and "--reference" in line and "readable" in line, line
    assert not (tmp_path / "o").exists()


def test_reference_missing_the_scene_is_refused(scene, tmp_path, capsys):
    far = write_raster(tmp_path / "far.tif", "EPSG:32610", 500000, 4000000)  # another continent
    line = refused(dsm_argv(scene, tmp_path / "o", *P1, "--reference", str(far)), capsys)
    assert str(far) in line and "--reference" in line and "covers none of the DSM grid" in line, line


def test_bounds_and_like_missing_the_scene_are_refused(scene, tmp_path, capsys):
    """Issue reproduction 5: they gave rc 0 and an all-NaN DSM."""
    g = truth_grid(scene)
    line = refused(dsm_argv(scene, tmp_path / "o", *P1, "--crs", g.crs, "--resolution", "0.5", "--bounds",
                            str(g.x0 + 5000), str(g.y0 - 100), str(g.x0 + 5100), str(g.y0)), capsys)
    assert line.startswith("tiledsm dsm: error: --bounds:") and "outside what the images see" in line, line
    far = write_raster(tmp_path / "like.tif", "EPSG:32610", 500000, 4000000)
    line = refused(dsm_argv(scene, tmp_path / "o", *P1, "--like", str(far)), capsys)
    assert f"--like {far}" in line and "outside what the images see" in line, line


@pytest.mark.slow
def test_grid_mostly_outside_the_images_warns_into_metrics(scene, tmp_path):
    """A grid of which 3/4 lies beyond the images: a warning on stderr and in metrics.json."""
    g = truth_grid(scene)
    x0, y0 = g.x0 + 64, g.y0 - 64  # the south-east quarter of the grid: 75 % beyond the views
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "tiledsm", "dsm", *map(str, scene.views), "--out", str(out), "--scheduler",
           "synchronous", "--no-progress", "--crs", g.crs, "--resolution", "0.5", "--bounds",
           str(x0), str(y0 - 256 * 0.5), str(x0 + 256 * 0.5), str(y0), *P1]
    r = run(cmd)
    _ok(r)
    assert "tiledsm dsm: warning: --bounds: the grid is mostly outside the images" in r.stderr, r.stderr
    assert any("mostly outside the images" in w for w in metrics(out)["warnings"])


def test_given_height_range_missing_the_tie_points_is_refused(scene, tmp_path, capsys):
    line = refused(dsm_argv(scene, tmp_path / "o", "--like", str(scene.truth_dsm), "--height-range", "0", "50"),
                   capsys)
    assert "--height-range 0 50" in line and "every cell would be NaN" in line, line


def test_sr_scale_without_weights_is_refused(scene, tmp_path, capsys):
    """Issue reproduction 5: sr.scale 3 passed the schema and failed much later."""
    line = refused(["sr", str(scene.views[0]), str(tmp_path / "x3"), "--model", "srcnn", "--scale", "3"], capsys)
    assert "--scale 3: no shipped weights for srcnn at x3" in line and "--weights" in line, line
    path = tmp_path / "sr.yaml"
    path.write_text(yaml.safe_dump({"pipeline": "sr_dsm", "input": {"synth": {"size": 128}},
                                    "sr": {"scale": 3, "models": ["dsm_upscale", "bicubic", "vdsr"]}}))
    line = refused(["run", str(path), "--out", str(tmp_path / "o")], capsys)
    assert "sr.scale: 3: no shipped weights for vdsr at x3" in line, line
    assert not (tmp_path / "o").exists()


def test_stable_mask_missing_the_scene_is_refused_before_any_dsm(scene, tmp_path, capsys):
    """Issue reproduction 5: compare.stable_mask of a deformation recipe was
    read only after both DSMs; ``tiledsm compare --stable-mask`` likewise."""
    g = truth_grid(scene)
    far = write_polygon(tmp_path / "far.geojson", g.crs, g.x0 + 5000, g.y0, 50)
    path = tmp_path / "def.yaml"
    views = [str(v) for v in scene.views]
    path.write_text(yaml.safe_dump({"pipeline": "deformation", "input": {"pre": {"images": views},
                                    "post": {"images": views}}, "compare": {"stable_mask": str(far)}}))
    line = refused(["run", str(path), "--out", str(tmp_path / "o")], capsys)
    assert f"{far}: compare.stable_mask: no polygon lies in the scene" in line, line
    assert not (tmp_path / "o").exists()
    line = refused(["compare", str(scene.truth_dsm), str(scene.truth_dsm), "--out", str(tmp_path / "c"),
                    "--stable-mask", str(far)], capsys)
    assert "--stable-mask: no polygon lies within REF's extent" in line, line


def test_stable_mask_that_excludes_nothing_warns(scene, tmp_path, capsys):
    """A polygon over cells without heights excludes nothing: a warning (stderr, plan)."""
    ref = write_raster(tmp_path / "ref.tif", "EPSG:32631", 600000, 4900000, shape=(64, 64), nan_rows=16)
    mask = write_polygon(tmp_path / "nan.geojson", "EPSG:32631", 600002, 4899998, 4)
    assert main(["compare", str(ref), str(ref), "--out", str(tmp_path / "c"), "--stable-mask", str(mask),
                 "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert "tiledsm compare: warning:" in captured.err and "excludes no valid cell" in captured.err, captured.err
    assert "excludes no valid cell" in captured.out


# ------------------------------------------------------------------ 1. interruptions
def _killed_when(cmd: list[str], ready, log: Path, tries: int = 3) -> int:
    """Start ``cmd``, SIGKILL its process group once ``ready()`` holds;
    returns the exit code (``-9`` when killed, else the run's own). A run
    that ended before ``ready()`` was seen is started again (``tries``
    times in all): a loaded machine may starve the polling."""
    for _ in range(tries):
        rc = _kill_once(cmd, ready, log)
        if rc != 0:
            return rc
    return rc


def _kill_once(cmd: list[str], ready, log: Path) -> int:
    with open(log, "w") as f:
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + 120
            while p.poll() is None and time.monotonic() < deadline:
                if ready():
                    os.killpg(p.pid, signal.SIGKILL)
                    break
                time.sleep(0.005)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)
    return p.returncode


def _consistent(out: Path) -> None:
    """Whatever describes the folder's products describes them: metrics and
    recipe, when present, have the stored DSM's height range."""
    fp = store_fingerprint(out / "dsm.zarr")["height_range"] if (out / "dsm.zarr").exists() else None
    if (out / "recipe.resolved.yaml").exists():
        assert recipe(out)["match"]["height_range"] == fp, (recipe(out)["match"], fp)
    if (out / "metrics.json").exists():
        assert metrics(out)["report"]["height_range_m"] == fp
    assert not ((out / "dsm.tif").exists() and not (out / "metrics.json").exists()) or fp is not None


@pytest.mark.slow
def test_interrupted_before_the_store_exists(scene, finished, tmp_path):
    """P2 --overwrite with no scheduler at its --scheduler address: the plan
    refuses it (issue 37) before anything is withdrawn, so the folder keeps
    P1's DSM and the products that describe it; P2 without --overwrite is
    then refused."""
    out = copy_of(finished, tmp_path)
    before = products(out)
    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P2, "--overwrite", scheduler="tcp://127.0.0.1:9"))
    assert r.returncode == 2 and "--scheduler tcp://127.0.0.1:9" in r.stderr, r.stderr
    assert store_fingerprint(out / "dsm.zarr")["height_range"] == [300.0, 350.0]
    assert products(out) == before
    _consistent(out)
    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P2))
    assert r.returncode == 2 and "height_range" in r.stderr and "--overwrite" in r.stderr, r.stderr
    _consistent(out)


@pytest.mark.slow
def test_interrupted_while_the_store_fills(scene, finished, tmp_path):
    """P2 --overwrite killed after 1..3 of its 4 chunks: P1's products are
    gone or withdrawn, and P2 run again resumes exactly those chunks (and
    says so), ending with a folder that describes P2."""
    out = copy_of(finished, tmp_path)
    partial = out / "dsm.zarr.partial"
    rc = _killed_when(dsm_cmd(scene.views, scene.truth_dsm, out, *P2, "--overwrite"),
                      lambda: (done_count(partial) or 0) >= 1, tmp_path / "killed.log")
    if rc == 0:
        pytest.skip("the run finished before it could be killed (machine too fast for the window)")
    k = done_count(partial)
    assert k is not None and 1 <= k < TOTAL, k
    assert not (out / "dsm.zarr").exists() and not (out / "metrics.json").exists()
    assert not (out / "recipe.resolved.yaml").exists() and not (out / "dsm.tif").exists()
    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P2))
    _ok(r)
    assert f"reused {k} of {TOTAL} chunks" in r.stdout
    assert metrics(out)["timings"]["chunks"] == {"chunks_total": TOTAL, "chunks_reused": k,
                                                 "chunks_computed": TOTAL - k}
    assert recipe(out)["match"]["height_range"] == [300.0, 360.0]
    _consistent(out)


@pytest.mark.slow
def test_interrupted_after_the_store_is_finished(scene, finished, tmp_path):
    """P2 --overwrite killed once its store is finished, before its
    metrics: nothing claims P1 beside P2's store; P2 again reuses every chunk."""
    out = copy_of(finished, tmp_path)

    def p2_finished() -> bool:
        try:  # P1's store is removed and P2's renamed under our feet
            return store_fingerprint(out / "dsm.zarr")["height_range"] == [300.0, 360.0]
        except Exception:
            return False

    rc = _killed_when(dsm_cmd(scene.views, scene.truth_dsm, out, *P2, "--overwrite"), p2_finished,
                      tmp_path / "killed.log")
    if rc == 0:
        pytest.skip("the run finished before it could be killed (machine too fast for the window)")
    assert store_fingerprint(out / "dsm.zarr")["height_range"] == [300.0, 360.0]
    assert not (out / "metrics.json").exists() and not (out / "recipe.resolved.yaml").exists()
    _consistent(out)
    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P2))
    _ok(r)
    assert metrics(out)["timings"]["chunks"]["chunks_reused"] == TOTAL
    _consistent(out)


@pytest.mark.slow
def test_refused_run_leaves_the_products_alone(scene, finished, tmp_path):
    out = copy_of(finished, tmp_path)
    before = products(out)
    r = run(dsm_cmd(scene.views, scene.truth_dsm, out, *P2))
    assert r.returncode == 2
    assert products(out) == before


# ------------------------------------------------------------------ 4. external cluster
@pytest.mark.slow
def test_relative_out_on_an_external_cluster(scene, tmp_path):
    """Issue reproduction 4: ``--out rel`` with ``--scheduler`` whose worker
    runs in another folder: the store lands in ``rel`` of the command's
    folder, not the worker's."""
    here, elsewhere = tmp_path / "here", tmp_path / "elsewhere"
    here.mkdir()
    elsewhere.mkdir()
    sched_file = tmp_path / "scheduler.json"
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    scheduler = subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--port", "0", "--dashboard-address", ":0",
                                  "--scheduler-file", str(sched_file)], cwd=elsewhere, env=env,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    worker = None
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists():
            assert time.monotonic() < deadline, "no scheduler within 60 s"
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        worker = subprocess.Popen([str(bin_dir / "dask"), "worker", address, "--nthreads", "1", "--nworkers", "1",
                                   "--no-dashboard"], cwd=elsewhere, env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        cmd = [sys.executable, "-m", "tiledsm", "dsm", *map(str, scene.views), "--like", str(scene.truth_dsm),
               "--out", "rel/out", "--scheduler", address, "--no-progress", *P1]
        r = subprocess.run(cmd, cwd=here, capture_output=True, text=True, timeout=240)
        _ok(r)
    finally:
        for p in (worker, scheduler):
            if p is not None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=30)
    assert (here / "rel" / "out" / "dsm.zarr").is_dir() and (here / "rel" / "out" / "metrics.json").exists()
    assert not (elsewhere / "rel").exists()


# ------------------------------------------------------------------ 6. messages
#: which commands can show the messages raised in a module (or one of its functions)
EMITTERS = {
    "tiledsm/provenance.py": ("dsm", "run", "ortho"),
    "tiledsm/io/stores.py": ("dsm", "run", "ortho"),
    "tiledsm/cli/synth.py": ("synth",),
    "tiledsm/sr/train.py": ("train-sr",),
    # `python -m tiledsm.sr.ncnn`, a maintainer's converter: no tiledsm command shows its options
    "tiledsm/sr/ncnn.py:main": (),
    "tiledsm/cli/orient.py": ("orient",),
    "tiledsm/orient/stage.py": ("orient",),
    "tiledsm/cli/ortho.py": ("ortho",),
    "tiledsm/ortho/stage.py": ("ortho",),
    "tiledsm/recipes.py:load_cluster": ("dsm", "run", "sr", "compare"),
    "tiledsm/io/atomic.py": ("dsm", "run"),
    "tiledsm/sr/registry.py": ("sr",),
    "tiledsm/cli/sr.py": ("sr",),
    "tiledsm/cli/dsm.py": ("dsm",),
    "tiledsm/cli/compare.py": ("compare",),
    "tiledsm/cli/displace.py": ("displace",),
    "tiledsm/evaluate/deformation.py": ("evaluate",),
    "tiledsm/evaluate/displacement.py": ("evaluate",),
    "tiledsm/evaluate/dsm.py": ("evaluate",),
    "tiledsm/evaluate/scenes.py": ("evaluate",),
    "tiledsm/evaluate/sr_dsm.py": ("evaluate",),
    "tiledsm/displace/grid.py": ("displace",),
    "tiledsm/workflows/displace.py": ("displace",),
    "tiledsm/cli/run.py": ("dsm", "run", "sr", "compare"),
    "tiledsm/plan/core.py": ("dsm", "run"),
    "tiledsm/dsm/plan.py": ("dsm", "run"),
    "tiledsm/plan/recipes.py": ("dsm", "run"),
    "tiledsm/sr/plan.py": ("sr", "run"),
    "tiledsm/compare/plan.py": ("compare", "run"),
    "tiledsm/sr/recipe.py": ("sr", "run"),
    "tiledsm/compare/recipe.py": ("compare", "run"),
    "tiledsm/plan/core.py:check_earlier_run": ("dsm", "run", "sr", "compare", "orient", "displace"),
    "tiledsm/ortho/plan.py": ("ortho", "run"),
    "tiledsm/orient/plan.py": ("orient", "run"),
    "tiledsm/io/lock.py:_refuse_or_take_over": ("dsm", "run", "compare", "ortho", "orient"),
    "tiledsm/plan/core.py:check_workers": ("dsm", "run", "compare", "sr"),
    "tiledsm/plan/core.py:FieldNames": ("dsm",),
    "tiledsm/cluster.py:compute_context": ("dsm", "run", "sr", "compare", "ortho", "orient"),
    "tiledsm/cluster.py:check_scheduler": ("dsm", "run", "sr", "compare", "ortho", "orient"),
}
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z-]*")


def _message_options() -> list[tuple[str, str, str]]:
    """``(module, enclosing function or class, option)`` of every
    ``--option`` in a string of tiledsm's code: docstrings, argparse
    declarations (``add_argument``) and their ``help``/``description`` left out."""
    import tiledsm

    root = Path(tiledsm.__file__).resolve().parent
    found = set()

    def visit(node, scope: str, module: str) -> None:
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            body[0].value.value = ""  # the docstring
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            scope = node.name
        if isinstance(node, ast.Call):
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            if name in ("add_argument", "add_parser", "ArgumentParser", "option"):
                return  # declarations; a spec's option() is checked by test_every_spec_option_exists_in_its_command
            for kw in node.keywords:
                if kw.arg in ("help", "description"):
                    kw.value = ast.Constant("")
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found.update((module, scope, o) for o in OPTION.findall(node.value))
        for child in ast.iter_child_nodes(node):
            visit(child, scope, module)

    for path in sorted(root.rglob("*.py")):
        visit(ast.parse(path.read_text()), "", "tiledsm/" + path.relative_to(root).as_posix())
    return sorted(found)


def test_every_option_a_message_names_exists_in_the_command_help():
    """Issue reproduction 6: "pass overwrite=True" named an option the CLI
    does not have. Every ``--option`` in a string of tiledsm's code (its
    messages) exists in the ``--help`` of each command that can show it
    (EMITTERS); the refusal tests above check each message they see."""
    found = _message_options()
    assert ("tiledsm/provenance.py", "check_resume", "--overwrite") in found
    problems = []
    for module, function, option in found:
        key = f"{module}:{function}"
        commands = EMITTERS[key] if key in EMITTERS else EMITTERS.get(module)
        if commands is None:
            problems.append(f"{module}:{function} names {option}: add the module to EMITTERS")
            continue
        problems += [f"{module}:{function}: `tiledsm {c}` has no {option}" for c in commands if option not in _help(c)]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("command, model", [
    ("dsm", "tiledsm.workflows.dsm:DSMRecipe"), ("displace", "tiledsm.workflows.displace:DisplaceRecipe"),
    ("sr", "tiledsm.sr.recipe:SRRecipe"), ("compare", "tiledsm.compare.recipe:CompareRecipe"),
    ("ortho", "tiledsm.ortho.recipe:OrthoRecipe"), ("orient", "tiledsm.orient.recipe:OrientRecipe")])
def test_every_spec_option_exists_in_its_command(command, model):
    """The options a command's spec names in its fields' metadata (what its
    errors print, :func:`tiledsm.recipes.options_of`) are the command's."""
    import importlib

    from tiledsm.recipes import options_of

    module, name = model.split(":")
    options = options_of(getattr(importlib.import_module(module), name))
    assert len(options) >= 8
    missing = [o for f, spelled in options.items() for o in spelled.split("/") if o.startswith("--") and o not in _help(command)]
    assert not missing, f"tiledsm {command} --help lacks {missing}"


def test_field_names_are_dsm_recipe_fields_spelled_by_the_command():
    """:class:`tiledsm.plan.FieldNames` lists the DSM recipe fields a plan's
    messages name: each is a field path of ``DSMRecipe`` (a renamed field
    cannot leave a stale name), and ``tiledsm dsm`` spells it with the
    option its spec's metadata names, which the command has (or with the
    path, for a field no option sets: ``input.rpcs``)."""
    from dataclasses import fields

    from pydantic import BaseModel

    from tiledsm.plan import RECIPE_NAMES, FieldNames
    from tiledsm.recipes import options_of
    from tiledsm.workflows.dsm import DSMRecipe

    def paths(model, prefix=""):
        for name, info in model.model_fields.items():
            yield prefix + name
            for arg in (info.annotation, *getattr(info.annotation, "__args__", ())):
                if isinstance(arg, type) and issubclass(arg, BaseModel):
                    yield from paths(arg, f"{prefix}{name}.")

    recipe_paths = set(paths(DSMRecipe))
    spelled = FieldNames.of_options(options_of(DSMRecipe))
    help_text = _help("dsm")
    for f in fields(FieldNames):
        path, option = getattr(RECIPE_NAMES, f.name), getattr(spelled, f.name)
        assert path in recipe_paths, f"FieldNames.{f.name}: {path} is no field of a DSM recipe"
        assert option == path or all(o in help_text for o in option.split("/") if o.startswith("--")), (f.name, option)
    assert (spelled.chunk, spelled.levels, spelled.images, spelled.rpcs) == ("--chunk", "--levels", "IMAGES", "input.rpcs")


# ------------------------------------------------------------------ memory
def test_worker_memory_formula():
    from tiledsm.dsm.memory import WORKER_BASELINE_MIB, estimate_worker_memory

    m = estimate_worker_memory((640, 640), 100, views=2, window_px=10**6, decimation=2, itemsize=2)
    held = 4 * 2 * 10**6 // 4
    assert m.cost_volumes == 2 * 4 * 640 * 640 * 100  # the fast kernel: volume and aggregated cost
    assert estimate_worker_memory((640, 640), 100, volumes=3).cost_volumes == 3 * 4 * 640 * 640 * 100
    assert m.matching == m.cost_volumes + 4 * 2 * 640 * 640 + held
    assert m.reading == 10**6 * 12 + held
    assert m.total == WORKER_BASELINE_MIB * 2**20 + m.matching
    banded = estimate_worker_memory((640, 640), 100, views=2, window_px=10**6, decimation=2, search_band=True)
    assert banded.matching == m.matching + 12 * 640 * 640


def test_worker_baseline_counts_the_cuda_context():
    """A worker matching on a CUDA device holds the CUDA context besides
    the usual baseline (measured: 209 MiB more, benchmarks/cuda_kernel.py);
    on the CPU, with either kernel, it does not."""
    from types import SimpleNamespace

    from tiledsm.match.sgvll import SGVLLParams
    from tiledsm.dsm.memory import CUDA_CONTEXT_MIB, WORKER_BASELINE_MIB, worker_baseline

    assert worker_baseline(SGVLLParams()) == WORKER_BASELINE_MIB * 2**20
    assert worker_baseline(SGVLLParams(kernel="reference")) == WORKER_BASELINE_MIB * 2**20
    # SGVLLParams refuses a CUDA device where numba sees none (as here): its two fields stand in
    on_gpu = SimpleNamespace(kernel="cuda", device="cuda:0")
    assert worker_baseline(on_gpu) == (WORKER_BASELINE_MIB + CUDA_CONTEXT_MIB) * 2**20


def test_plan_levels_match_the_built_graph(scene):
    """The plan's level sizes are the lazy DSM's own: as many matching tasks
    per level as the graph's ``match-L<level>-<token>`` layer holds."""
    from tiledsm.pipelines import plan_recipe
    from tiledsm.workflows.dsm import DSMRecipe

    for chunk, levels in ((64, 2), (128, 2), (256, 1), (128, 3)):
        r = DSMRecipe.model_validate({"pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
                                      "grid": {"like": str(scene.truth_dsm), "chunk": chunk},
                                      "match": {"levels": levels, "height_range": [300, 350]}})
        plan = plan_recipe(r, scene.out_dir / "never")
        graph = plan.prepared.ds.__dask_graph__()
        assert [lv.level for lv in plan.levels] == list(range(levels - 1, -1, -1))
        for lv in plan.levels:
            assert lv.shape == (-(-256 // 2**lv.level),) * 2
            (layer,) = [name for name in graph.layers if name.startswith(f"match-L{lv.level}-")]
            assert lv.chunks == len(graph.layers[layer]), (chunk, lv)
        assert plan.tasks == len(graph)
        assert plan.memory.total > plan.memory.baseline
    assert not (scene.out_dir / "never").exists()


def test_plan_task_sizes_and_candidates(scene):
    """Largest task = chunk grown to the paths' restart lines plus half a
    window (clipped at the grid's edges); candidates: the whole range at the
    coarsest level, the band (25) below."""
    from tiledsm.pipelines import plan_recipe
    from tiledsm.workflows.dsm import DSMRecipe

    r = DSMRecipe.model_validate({"pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
                                  "grid": {"like": str(scene.truth_dsm), "chunk": 90},
                                  "match": {"levels": 2, "height_range": [300, 350]}})
    plan = plan_recipe(r, scene.out_dir / "never")
    coarse, fine = plan.levels
    assert coarse.task_cells == (128, 128) and coarse.chunks == 1
    # chunks [90, 166] on each axis (the last 76 cells merged): the second one from the restart line
    # at 64 less half a window (62) to the grid's edge
    assert fine.task_cells == (256 - 62, 256 - 62) and fine.chunks == 4
    assert coarse.candidates == int(np.ceil(50 / coarse.step - 1e-9)) + 1
    assert fine.candidates == 25
