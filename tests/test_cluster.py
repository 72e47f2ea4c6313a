"""Where dask runs: recipe ``cluster`` sections, ``--cluster FILE``, and
batch-system jobs through dask-jobqueue.

The job scripts are checked for the resources asked for (no batch system
is needed to generate them). One test runs a real DSM on a "SLURM" whose
``sbatch`` is a stand-in script that starts the job script on this machine
(and ``scancel`` kills it): the workers are started by the generated job
script exactly as a cluster node would start them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tiledsm.cluster import JobQueueConfig, job_script
from tiledsm.errors import InvalidOptionError, RecipeError
from tiledsm.recipes import ClusterSpec, load_cluster

JOB = {
    "cores": 8, "memory": "32GiB", "walltime": "02:30:00", "queue": "normal", "account": "proj1",
    "job_extra_directives": [], "minimum_jobs": 1, "maximum_jobs": 4,
}


def _script(kind: str, **extra) -> str:
    spec = ClusterSpec.model_validate({"kind": kind, "jobqueue": {**JOB, **extra}})
    return job_script(spec.config().jobqueue)


def test_slurm_job_script_asks_for_the_resources():
    s = _script("slurm", job_extra_directives=["--constraint=skylake"], processes=4)
    for line in ("#SBATCH -p normal", "#SBATCH -A proj1", "#SBATCH --cpus-per-task=8", "#SBATCH --mem=32G",
                 "#SBATCH -t 02:30:00", "#SBATCH --constraint=skylake"):
        assert line in s, (line, s)
    # 4 workers of 8 / 4 threads sharing the job's memory, one thread per native library
    assert "--nworkers 4" in s and "--nthreads 2" in s and "--memory-limit 8.00GiB" in s, s
    assert "export OMP_NUM_THREADS=1" in s and "export NUMBA_NUM_THREADS=1" in s
    assert sys.executable in s


def test_pbs_job_script_asks_for_the_resources():
    s = _script("pbs")
    for line in ("#PBS -q normal", "#PBS -A proj1", "#PBS -l select=1:ncpus=8:mem=32GB", "#PBS -l walltime=02:30:00"):
        assert line in s, (line, s)
    # by default one single-threaded worker per core, as on a local cluster
    assert "--nworkers 8" in s and "--nthreads 1" in s and "--memory-limit 4.00GiB" in s, s


def test_sge_job_script_asks_for_the_resources():
    s = _script("sge", job_extra_directives=["-P proj1"])
    for line in ("#$ -q normal", "#$ -l h_vmem=32GiB", "#$ -l h_rt=02:30:00", "#$ -P proj1"):
        assert line in s, (line, s)


@pytest.mark.parametrize(
    "section, field",
    [
        ({"kind": "address"}, "address"),
        ({"kind": "local", "jobqueue": {"cores": 2}}, "jobqueue"),
        ({"kind": "slurm", "workers": 4}, "workers"),
        ({"kind": "slurm", "scheduler": "tcp://h:1"}, "scheduler"),
        ({"kind": "slurm", "jobqueue": {"walltime": "2h"}}, "walltime"),
        ({"kind": "lsf"}, "kind"),
        ({"kind": "slurm", "jobqueue": {"cores": 2, "memry": "4GiB"}}, "memry"),
    ],
)
def test_bad_cluster_sections_name_the_field(tmp_path, section, field):
    f = tmp_path / "cluster.yaml"
    f.write_text(yaml.safe_dump({"cluster": section}))
    with pytest.raises(RecipeError) as e:
        load_cluster(f)
    assert field in str(e.value) and str(f) in str(e.value)


def test_jobqueue_config_checks_its_numbers():
    with pytest.raises(InvalidOptionError, match="processes"):
        JobQueueConfig("slurm", cores=2, processes=3)
    with pytest.raises(InvalidOptionError, match="minimum_jobs"):
        JobQueueConfig("pbs", minimum_jobs=3, maximum_jobs=2)


def _cli(*args: str, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tiledsm", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from tiledsm.synth import make_scene

    return make_scene(tmp_path_factory.mktemp("scene"), size=192, gsd=0.5, bh=0.4, seed=5, views=2)


def test_cluster_file_shows_in_the_plan(scene, tmp_path):
    """``--cluster FILE`` with a SLURM section: the dry run names the jobs
    and their resources (nothing is submitted)."""
    f = tmp_path / "slurm.yaml"
    f.write_text(yaml.safe_dump({"kind": "slurm", "jobqueue": JOB}))
    r = _cli("dsm", *map(str, scene.views), "--like", str(scene.truth_dsm), "--out", str(tmp_path / "o"),
             "--cluster", str(f), "--dry-run")
    assert r.returncode == 0, r.stderr[-2000:]
    line = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith("cluster"))
    assert "slurm jobs (dask-jobqueue): 1..4 jobs of 8 cores, 32GiB, 02:30:00" in line, line
    assert "queue normal" in line and "account proj1" in line, line
    assert not (tmp_path / "o").exists()
    # --workers cannot size a batch cluster
    r = _cli("dsm", *map(str, scene.views), "--like", str(scene.truth_dsm), "--out", str(tmp_path / "o"),
             "--cluster", str(f), "--workers", "2", "--dry-run")
    assert r.returncode == 2 and "--scheduler/--workers" in r.stderr and "Traceback" not in r.stderr, r.stderr


FAKE_SBATCH = """#!/usr/bin/env bash
# stand-in for SLURM's sbatch: run the job script here, detached
cp "$1" "{jobs}/job_$$.sh"
setsid bash "{jobs}/job_$$.sh" > "{jobs}/job_$$.log" 2>&1 < /dev/null &
echo $! > "{jobs}/job_$$.pid"
echo "Submitted batch job $!"
"""
FAKE_SCANCEL = """#!/usr/bin/env bash
for id in "$@"; do kill -TERM -- "-$id" 2>/dev/null || kill -TERM "$id" 2>/dev/null; done
exit 0
"""


@pytest.mark.slow
def test_dsm_on_slurm_jobs_equals_the_local_dsm(scene, tmp_path):
    """A recipe with ``cluster: {kind: slurm}`` computes its DSM on workers
    started by the generated job script (through a stand-in ``sbatch``),
    bit-identical to the same recipe on a local cluster."""
    import numpy as np

    from tiledsm.io import open_product

    bin_dir, jobs = tmp_path / "bin", tmp_path / "jobs"
    bin_dir.mkdir()
    jobs.mkdir()
    for name, text in (("sbatch", FAKE_SBATCH.format(jobs=jobs)), ("scancel", FAKE_SCANCEL), ("squeue", "#!/bin/sh\nexit 0\n")):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    base = {
        "pipeline": "dsm", "input": {"images": [str(v) for v in scene.views]},
        "grid": {"like": str(scene.truth_dsm), "chunk": 96}, "match": {"levels": 1},
        "output": {"cog": False, "quicklook": False},
    }
    runs = {}
    for name, cluster in (
        ("slurm", {"kind": "slurm", "jobqueue": {"cores": 2, "memory": "4GiB", "walltime": "00:10:00"}}),
        ("local", {"kind": "local", "workers": 2}),
    ):
        rec = tmp_path / f"{name}.yaml"
        rec.write_text(yaml.safe_dump({**base, "name": name, "cluster": cluster}))
        r = _cli("run", str(rec), "--out", str(tmp_path / name), "--no-progress", env=env)
        assert r.returncode == 0, f"{name}: rc {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
        runs[name] = open_product(tmp_path / name / "dsm.zarr")["height"].values
    logs = sorted(jobs.glob("job_*.log"))
    assert logs, "no job was submitted through sbatch"
    assert any("Starting Worker" in p.read_text() or "Start worker" in p.read_text() for p in logs), \
        "\n".join(p.read_text()[-1500:] for p in logs)
    np.testing.assert_array_equal(runs["slurm"], runs["local"])
    assert np.isfinite(runs["slurm"]).mean() > 0.8
    metrics = json.loads((tmp_path / "slurm" / "metrics.json").read_text())
    assert metrics["timings"]["chunks"]["chunks_computed"] == 4


def _slurm_node_idle() -> bool:
    import shutil

    if not shutil.which("sinfo"):
        return False
    r = subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True)
    return r.returncode == 0 and "idle" in r.stdout.split()


@pytest.mark.slow
@pytest.mark.skipif(not _slurm_node_idle(), reason="no SLURM with an idle node here (benchmarks/slurm_local.sh starts one)")
def test_dsm_on_a_real_slurm_equals_the_local_dsm(tmp_path):
    """Where a real SLURM runs (``sudo benchmarks/slurm_local.sh start``):
    ``benchmarks/slurm_run.py`` submits the workers as SLURM jobs through
    ``--cluster slurm.yaml``, and the DSM equals the local one cell by cell."""
    out = tmp_path / "slurm_run.json"
    r = subprocess.run([sys.executable, str(Path(__file__).parents[1] / "benchmarks" / "slurm_run.py"), "--size", "256",
                        "--json", str(out), "--workdir", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["jobs_submitted"] >= 1 and result["heights_identical"] and result["cells_differing"] == 0, result
    assert result["chunks"]["chunks_computed"] == 4 and result["finite_fraction"] > 0.8, result
