"""A worker's memory budget (issue 14): the plan sizes the DSM's chunks for
it when no chunk is given, refuses a given chunk beyond it, the run uses the
chunk the plan chose (and says so in ``recipe.resolved.yaml``), and a
worker stopped at its memory limit ends the run with one clear line."""

from __future__ import annotations

import time

import dask
import dask.array as da
import numpy as np
import pytest
import yaml

from tiledsm.cli import main
from tiledsm.cluster import ClusterConfig, compute_context, worker_memory_budget
from tiledsm.errors import InvalidOptionError, WorkerMemoryError
from tiledsm.io import open_product
from tiledsm.pipelines import plan_recipe
from tiledsm.synth import make_scene
from tiledsm.workflows.dsm import DSMRecipe

FAST = {"levels": 1}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("scene"), size=256, gsd=0.5, bh=0.4, seed=5, views=2)


def _plan(scene, out, memory: str = "auto", **grid):
    recipe = DSMRecipe.model_validate({"pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
                                       "grid": {"like": str(scene.truth_dsm), **grid}, "match": FAST})
    return plan_recipe(recipe, out, ClusterConfig(scheduler="synchronous", memory_limit=memory))


def test_budget_of_each_kind_of_cluster():
    from tiledsm.cluster import JobQueueConfig

    assert worker_memory_budget(ClusterConfig(memory_limit="3GiB")) == 3 * 2**30
    assert worker_memory_budget(ClusterConfig(jobqueue=JobQueueConfig("slurm", cores=4, memory="16GiB"))) == 4 * 2**30
    assert worker_memory_budget(ClusterConfig(scheduler="tcp://h:8786")) is None  # the workers' own business
    import psutil

    assert worker_memory_budget(ClusterConfig(workers=2)) == psutil.virtual_memory().total // 2


def test_default_chunk_shrinks_to_fit_a_worker(scene, tmp_path):
    # the oracle: each chunk side planned explicitly
    need = {c: _plan(scene, tmp_path / f"c{c}", chunk=c).memory.total for c in (512, 384, 256, 192, 128, 96)}
    budget = need[96] + 2**20  # only chunks as light as 96's fit
    expected = max(c for c, n in need.items() if n <= budget)
    assert need[expected] < need[512]
    fitted = _plan(scene, tmp_path / "fit", memory=str(budget))
    assert fitted.recipe.grid.chunk == expected and fitted.prepared.grid.chunk == expected
    assert fitted.memory.total == need[expected] <= budget
    assert any(f"chunks of {expected} chosen to fit a worker's memory" in n for n in fitted.notes)
    assert _plan(scene, tmp_path / "roomy", memory=str(need[512])).recipe is None  # nothing changes when it fits


def test_given_chunk_beyond_the_budget_is_refused(scene, tmp_path, capsys):
    default = _plan(scene, tmp_path / "a")
    budget = default.memory.total - 2**20
    with pytest.raises(InvalidOptionError, match=r"grid.chunk 512: a worker would need ~.* beyond its memory"):
        _plan(scene, tmp_path / "b", memory=str(budget), chunk=512)
    rc = main(["dsm", *map(str, scene.views), "--like", str(scene.truth_dsm), "--out", str(tmp_path / "c"),
               "--chunk", "512", "--memory-per-worker", f"{budget}B", "--scheduler", "synchronous"])
    err = capsys.readouterr().err
    assert rc == 2 and "--chunk 512: a worker would need" in err and not (tmp_path / "c").exists()


def test_run_uses_the_chosen_chunk(scene, tmp_path):
    need = {c: _plan(scene, tmp_path / f"c{c}", chunk=c).memory.total for c in (512, 384, 256, 192, 128, 96)}
    budget = need[96] + 2**20
    expected = max(c for c, n in need.items() if n <= budget)
    out = tmp_path / "run"
    rc = main(["dsm", *map(str, scene.views), "--like", str(scene.truth_dsm), "--out", str(out), "--levels", "1",
               "--memory-per-worker", f"{budget}B", "--scheduler", "synchronous", "--no-progress"])
    assert rc == 0 and expected < 512
    height = open_product(out / "dsm.zarr")["height"]
    assert height.data.chunks[0][0] == expected
    assert yaml.safe_load((out / "recipe.resolved.yaml").read_text())["grid"]["chunk"] == expected


def test_a_worker_killed_at_its_memory_limit_is_one_clear_error():
    def hog(block):
        held = np.ones(700 * 2**20 // 8)  # 700 MiB, beyond the 400 MiB limit
        time.sleep(5)  # the nanny samples memory every 100 ms
        return block + held[:1]

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with pytest.raises(WorkerMemoryError, match=r"memory limit: 400\.00 MiB per worker.*smaller chunks"):
            with compute_context(ClusterConfig(workers=1, memory_limit="400MiB", progress=False)):
                da.map_blocks(hog, da.zeros(2, chunks=1), dtype=float).compute()


# ------------------------------------------------------------------ on a GPU
def test_gpu_memory_of_a_task():
    """The GPU's share of a task (the formula of estimate_worker_memory):
    volume and aggregated costs, samples (the band's wider span below the
    coarsest level), image windows, per-cell arrays; none on the CPU."""
    from tiledsm.dsm.memory import SAMPLE_SPAN, estimate_worker_memory

    cells, nd, nv, W, f = 600 * 500, 40, 3, 10**6, 2
    held = 4 * nv * W // (f * f)
    coarse = estimate_worker_memory((600, 500), nd, nv, W, f, on_device=True)
    assert coarse.device == 8 * cells * nd + 4 * nv * cells * nd + held + 56 * cells
    band = estimate_worker_memory((600, 500), nd, nv, W, f, search_band=True, on_device=True)
    assert band.device == 8 * cells * nd + 4 * nv * cells * int(SAMPLE_SPAN * nd) + held + 56 * cells
    assert estimate_worker_memory((600, 500), nd, nv, W, f).device == 0
    assert "GPU ~" in coarse.text() and "GPU" not in estimate_worker_memory((600, 500), nd).text()


def test_tasks_per_gpu_of_each_kind_of_cluster():
    from tiledsm.cluster import JobQueueConfig, tasks_per_device

    assert tasks_per_device(ClusterConfig(workers=3)) == 3
    assert tasks_per_device(ClusterConfig(scheduler="threads", workers=16)) == 16
    assert tasks_per_device(ClusterConfig(scheduler="synchronous")) == 1
    assert tasks_per_device(ClusterConfig(jobqueue=JobQueueConfig("slurm", cores=8, processes=4, memory="16GiB"))) == 4
    assert tasks_per_device(ClusterConfig(scheduler="tcp://h:8786")) is None


@pytest.fixture
def pretend_gpu(monkeypatch):
    """A CUDA device with ``free`` bytes (set by the test) for the plan:
    the kernel's device check passes and the GPU's memory is ``free``."""
    import dataclasses

    from tiledsm.match import cuda_kernel
    from tiledsm.match.kernels import KERNELS

    monkeypatch.setitem(KERNELS, "cuda", dataclasses.replace(KERNELS["cuda"], check_device=lambda device: None))
    gpu = {"free": 80 * 2**30}
    monkeypatch.setattr(cuda_kernel, "memory_info", lambda device: (gpu["free"], 80 * 2**30))
    return gpu


def _gpu_plan(scene, out, workers: int = 2, device: str = "cuda", **grid):
    recipe = DSMRecipe.model_validate({
        "pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
        "grid": {"like": str(scene.truth_dsm), **grid},
        "match": {**FAST, "params": {"kernel": "cuda", "device": device}}})
    return plan_recipe(recipe, out, ClusterConfig(scheduler="threads", workers=workers))


def test_default_chunk_shrinks_to_fit_a_gpu(scene, tmp_path, pretend_gpu):
    from tiledsm.dsm.plan import GPU_USABLE

    # the oracle: each chunk side planned explicitly (on the 256² scene,
    # measured: 63 MiB for one task of the whole grid from chunks of 192 up,
    # 16 MiB at chunks of 128)
    need = {c: _gpu_plan(scene, tmp_path / f"c{c}", chunk=c).memory.device for c in (512, 256, 192, 128)}
    assert need[128] < need[192] == need[256] == need[512]
    # 2 tasks at once, each GPU_USABLE of half the free memory: 128 fits, 192 does not
    pretend_gpu["free"] = int((need[128] + 2**10) * 2 / GPU_USABLE)
    fitted = _gpu_plan(scene, tmp_path / "fit")
    assert fitted.recipe.grid.chunk == 128 and fitted.memory.device == need[128]
    assert any("chunks of 128 chosen to fit a task's share of the free memory of GPU cuda (2 tasks at once)" in n
               for n in fitted.notes)
    # a given chunk beyond it is refused, naming the chunk and the GPU
    with pytest.raises(InvalidOptionError, match=r"grid.chunk 512: a task would need on the GPU ~.* beyond its "
                                                 r"share of the free memory of GPU cuda \(2 tasks at once\)"):
        _gpu_plan(scene, tmp_path / "given", chunk=512)
    # two GPUs share four threads: still 2 tasks on each, the same fit
    two = _gpu_plan(scene, tmp_path / "two", workers=4, device="cuda:0,1")
    assert two.recipe.grid.chunk == 128
    assert any("free memory of GPU cuda:0,1 (2 tasks at once)" in n for n in two.notes)
    # a GPU too small for any chunk tried: refused, naming what to change
    pretend_gpu["free"] = 2**20
    with pytest.raises(InvalidOptionError, match=r"grid.chunk: even the smallest chunk tried .* GPU cuda .*--workers"):
        _gpu_plan(scene, tmp_path / "tiny")
