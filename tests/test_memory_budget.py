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
from tiledsm.plan import plan_recipe
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
