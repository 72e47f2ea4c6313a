"""Where dask runs: a local cluster by default, or an existing scheduler.

Default: a :class:`distributed.LocalCluster` with one single-threaded worker
process per core, so numba, OpenCV and torch each use one thread inside a
task and tasks never oversubscribe the cores. ``scheduler="tcp://host:8786"``
runs the same graph on an existing cluster (dask-jobqueue, dask-kubernetes,
``dask scheduler`` + ``dask worker``). ``scheduler="synchronous"`` runs in
the calling thread (tests, debugging).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Iterator

import dask

__all__ = ["ClusterConfig", "compute_context", "shared_cluster", "single_threaded_libraries"]

#: environment that keeps native libraries to one thread inside a task
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


@dataclass(frozen=True)
class ClusterConfig:
    """How to execute dask graphs.

    Attributes
    ----------
    scheduler : str or None
        ``None`` for a new local cluster, ``"synchronous"`` for in-thread
        execution, or a scheduler address (``tcp://host:8786``).
    workers : int or None
        Number of local worker processes (default: number of cores).
    memory_limit : str
        Per-worker memory limit of a local cluster (dask syntax).
    progress : bool
        Show a progress bar.
    """

    scheduler: str | None = None
    workers: int | None = None
    memory_limit: str = "auto"
    progress: bool = True


def single_threaded_libraries() -> None:
    """Ask OpenCV and torch (when imported) to use one thread in this process."""
    for key, value in SINGLE_THREAD_ENV.items():
        os.environ.setdefault(key, value)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover - cv2 is a dependency
        pass
    import sys

    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


@contextlib.contextmanager
def compute_context(config: ClusterConfig = ClusterConfig()) -> Iterator[object | None]:
    """Context in which ``dask.compute`` runs on the configured scheduler.

    Yields the :class:`distributed.Client` (or ``None`` when synchronous).
    """
    if config.scheduler == "synchronous":
        with dask.config.set(scheduler="synchronous"):
            yield None
        return
    from distributed import Client, LocalCluster

    if config.scheduler:
        with Client(config.scheduler) as client:
            client.run(single_threaded_libraries)
            yield client
        return
    n = config.workers or os.cpu_count() or 1
    # Workers inherit the environment at spawn: set it before they start.
    for key, value in SINGLE_THREAD_ENV.items():
        os.environ.setdefault(key, value)
    with LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        memory_limit=config.memory_limit,
        dashboard_address=":0",  # a free port: no clash with a running cluster
    ) as cluster, Client(cluster) as client:
        client.run(single_threaded_libraries)
        yield client


@contextlib.contextmanager
def shared_cluster(config: ClusterConfig = ClusterConfig()) -> Iterator[ClusterConfig]:
    """One cluster for a run of several stages: yields a configuration whose
    ``scheduler`` is the address of a local cluster started once (each
    stage's :func:`compute_context` then connects to it instead of starting
    its own); an explicit scheduler or ``"synchronous"`` is yielded as is."""
    if config.scheduler is not None:
        yield config
        return
    import dataclasses

    with compute_context(config) as client:
        yield dataclasses.replace(config, scheduler=client.scheduler.address)


def compute_with_progress(*collections, config: ClusterConfig = ClusterConfig(), client=None):
    """``dask.compute`` with a progress bar suited to the scheduler in use."""
    if not config.progress:
        return dask.compute(*collections)
    if client is not None:
        from distributed import progress

        futures = client.compute(list(collections))
        progress(futures)
        print()
        return tuple(f.result() for f in futures)
    from dask.diagnostics import ProgressBar

    with ProgressBar(dt=1.0):
        return dask.compute(*collections)
