"""Where dask runs: a local cluster by default, an existing scheduler, or
jobs of a batch system.

Default: a :class:`distributed.LocalCluster` with one single-threaded worker
process per core, so numba, OpenCV and torch each use one thread inside a
task and tasks never oversubscribe the cores. ``scheduler="tcp://host:8786"``
runs the same graph on an existing cluster (dask-kubernetes, ``dask
scheduler`` + ``dask worker``). ``scheduler="threads"`` runs on ``workers``
threads of the calling process (dask's threaded scheduler): no worker
process to start and no block copied between processes, for work whose
kernels release the GIL (numpy, numba ``nogil``, GDAL), such as ``compare``
on one machine; no per-worker memory limit is enforced then.
``scheduler="synchronous"`` runs in the calling thread (tests, debugging). ``jobqueue=JobQueueConfig("slurm", ...)``
starts the workers as SLURM, PBS or SGE jobs through dask-jobqueue (the
scheduler runs in the calling process, typically on a login node; jobs are
submitted adaptively between ``minimum_jobs`` and ``maximum_jobs``), each
job running ``processes`` single-threaded workers.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Iterator

import dask

__all__ = [
    "ClusterConfig",
    "JobQueueConfig",
    "SCHEDULER_TIMEOUT_S",
    "check_scheduler",
    "JOBQUEUE_KINDS",
    "compute_context",
    "jobqueue_cluster",
    "job_script",
    "shared_cluster",
    "single_threaded_libraries",
    "tasks_per_device",
    "worker_memory_budget",
]

#: batch systems and their dask-jobqueue cluster class
JOBQUEUE_KINDS = {"slurm": "SLURMCluster", "pbs": "PBSCluster", "sge": "SGECluster"}

#: environment that keeps native libraries to one thread inside a task
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


@dataclass(frozen=True)
class JobQueueConfig:
    """Workers as jobs of a batch system (dask-jobqueue).

    Attributes
    ----------
    kind : str
        ``"slurm"``, ``"pbs"`` or ``"sge"`` (:data:`JOBQUEUE_KINDS`).
    cores : int
        Cores per job; the job runs ``processes`` workers of
        ``cores / processes`` threads each (default: ``cores``
        single-threaded workers, as on a local cluster; fewer processes
        give each worker more memory).
    memory : str
        Memory per job (dask syntax, e.g. ``"32GiB"``); each worker's limit
        is ``memory / processes``, and dask stops a worker that exceeds it
        rather than letting the node swap.
    walltime : str
        Job time limit, ``HH:MM:SS``.
    queue, account : str or None
        Partition/queue and project to charge.
    processes : int or None
        Workers per job (default ``cores``).
    job_extra_directives : tuple of str
        Extra scheduler directives, e.g. ``("--constraint=skylake",)``.
    minimum_jobs, maximum_jobs : int
        Bounds of the adaptive job count.
    local_directory : str or None
        Worker scratch space on the node (e.g. ``"$TMPDIR"``).
    interface : str or None
        Network interface of the workers (e.g. ``"ib0"``).
    python : str or None
        Python on the nodes (default: the one running tiledsm).
    """

    kind: str
    cores: int = 1
    memory: str = "4GiB"
    walltime: str = "01:00:00"
    queue: str | None = None
    account: str | None = None
    processes: int | None = None
    job_extra_directives: tuple[str, ...] = ()
    minimum_jobs: int = 1
    maximum_jobs: int = 1
    local_directory: str | None = None
    interface: str | None = None
    python: str | None = None

    def __post_init__(self) -> None:
        from tiledsm.errors import InvalidOptionError

        if self.kind not in JOBQUEUE_KINDS:
            raise InvalidOptionError(f"cluster kind {self.kind!r}: expected one of {sorted(JOBQUEUE_KINDS)}")
        if self.cores < 1 or (self.processes is not None and not 1 <= self.processes <= self.cores):
            raise InvalidOptionError(
                f"cluster: cores must be >= 1 and processes between 1 and cores, got cores={self.cores}, "
                f"processes={self.processes}"
            )
        if not 0 <= self.minimum_jobs <= self.maximum_jobs or self.maximum_jobs < 1:
            raise InvalidOptionError(
                f"cluster: need 0 <= minimum_jobs <= maximum_jobs and maximum_jobs >= 1, got "
                f"{self.minimum_jobs}..{self.maximum_jobs}"
            )

    def cluster_kwargs(self) -> dict:
        """Keyword arguments of the dask-jobqueue cluster class."""
        import sys

        kw = dict(
            cores=self.cores,
            processes=self.processes or self.cores,
            memory=self.memory,
            walltime=self.walltime,
            queue=self.queue,
            account=self.account,
            job_extra_directives=list(self.job_extra_directives),
            # one thread per worker: native libraries too, set before the worker starts
            job_script_prologue=[f"export {k}={v}" for k, v in SINGLE_THREAD_ENV.items()],
            python=self.python or sys.executable,
            local_directory=self.local_directory,
            interface=self.interface,
            scheduler_options={"dashboard_address": ":0"},  # a free port: no clash with another cluster
        )
        if self.kind == "sge":
            kw.pop("account")  # SGE has projects, set through job_extra_directives ("-P name")
            kw["resource_spec"] = f"h_vmem={self.memory}"
        return {k: v for k, v in kw.items() if v is not None}


@dataclass(frozen=True)
class ClusterConfig:
    """How to execute dask graphs.

    Attributes
    ----------
    scheduler : str or None
        ``None`` for a new local cluster, ``"threads"`` for ``workers``
        threads of this process, ``"synchronous"`` for in-thread
        execution, or a scheduler address (``tcp://host:8786``).
    workers : int or None
        Number of local worker processes (default: number of cores).
    memory_limit : str
        Memory of each worker (dask syntax, e.g. ``"4GiB"``): the limit at
        which a local cluster's nanny stops a worker, and the budget the
        plan sizes chunks for (:func:`worker_memory_budget`). ``"auto"``:
        the machine's memory divided among the local workers.
    progress : bool
        Show a progress bar.
    jobqueue : JobQueueConfig or None
        Start the workers as batch jobs instead (``scheduler`` must then
        be ``None``).
    """

    scheduler: str | None = None
    workers: int | None = None
    memory_limit: str = "auto"
    progress: bool = True
    jobqueue: JobQueueConfig | None = None

    @property
    def local_workers(self) -> int:
        """Local workers or threads to start: ``workers``, else one per core."""
        return self.workers or os.cpu_count() or 1

    def __post_init__(self) -> None:
        if self.jobqueue is not None and self.scheduler is not None:
            from tiledsm.errors import InvalidOptionError

            raise InvalidOptionError(
                f"cluster: a {self.jobqueue.kind} cluster starts its own scheduler; do not also give "
                f"a scheduler ({self.scheduler!r})"
            )


#: seconds the plan gives a ``--scheduler`` address to answer as a dask scheduler
SCHEDULER_TIMEOUT_S = 3.0
#: the largest first message a dask scheduler sends (its handshake: a few hundred bytes)
_HANDSHAKE_MAX_BYTES = 1 << 20


def check_scheduler(address: str, name: str = "--scheduler", timeout: float = SCHEDULER_TIMEOUT_S) -> int:
    """Contact the dask scheduler at ``address`` and return its number of
    workers, within about ``2 * timeout`` seconds whatever is (or is not)
    listening there.

    A TCP address is first probed with a plain socket: the host must
    resolve, the port accept, and what answers must send dask's handshake
    (a scheduler writes it as soon as it accepts: an 8-byte length, then
    that many bytes naming its pickle protocol). Only then does a
    :class:`distributed.Client` connect and ask for the workers -- a
    client connecting straight to something else waits until that peer
    hangs up, or reads a text as a frame length and tries to allocate
    exabytes. Other schemes (``tls://``, ``inproc://``, ``ucx://``) are
    checked by the client alone.

    Raises
    ------
    InvalidOptionError
        Naming ``name`` and ``address`` and what went wrong, before
        anything is written.
    """
    from distributed import Client
    from distributed.comm import parse_address, parse_host_port

    from tiledsm.errors import InvalidOptionError

    def refuse(problem: str) -> InvalidOptionError:
        return InvalidOptionError(f"{name} {address}: {problem}")

    try:
        scheme, location = parse_address(address)
        if scheme == "tcp":
            _probe_tcp(*parse_host_port(location), timeout, refuse)
    except ValueError as exc:
        raise refuse(f"not a scheduler address ({exc}); expected tcp://host:port") from None
    try:
        with Client(address, timeout=timeout, set_as_default=False) as client:
            return len(client.scheduler_info()["workers"])
    except Exception as exc:  # noqa: BLE001 - whatever the peer did, the address is wrong
        raise refuse(f"no dask scheduler answers there ({type(exc).__name__}: {exc})") from None


def _probe_tcp(host: str, port: int, timeout: float, refuse) -> None:
    """Raise ``refuse(problem)`` unless a dask scheduler's handshake comes
    back from ``host:port`` within ``timeout`` seconds."""
    import socket
    import struct

    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise refuse(f"cannot resolve the host {host!r} ({exc.strerror})") from None
    try:
        conn = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else exc.strerror or str(exc)
        raise refuse(f"nothing accepts a connection there ({reason})") from None
    not_dask = "something listens there but it is not a dask scheduler"
    with conn:
        try:
            head = _read_exactly(conn, 8)
            (size,) = struct.unpack("<Q", head)
            if not 8 < size <= _HANDSHAKE_MAX_BYTES:
                raise refuse(f"{not_dask} (its first bytes are {head!r})")
            if b"pickle-protocol" not in _read_exactly(conn, size):
                raise refuse(f"{not_dask} (its first message is no dask handshake)")
        except TimeoutError:
            raise refuse(f"{not_dask} (it sent no handshake within {timeout:g} s)") from None
        except (ConnectionError, EOFError) as exc:
            raise refuse(f"{not_dask} (it closed the connection: {exc})") from None


def _read_exactly(conn, n: int) -> bytes:
    """``n`` bytes from a socket (its timeout applies to each read)."""
    data = b""
    while len(data) < n:
        part = conn.recv(min(n - len(data), 65536))
        if not part:
            raise EOFError(f"closed after {len(data)} of {n} bytes")
        data += part
    return data


def jobqueue_cluster(config: JobQueueConfig):
    """The dask-jobqueue cluster of ``config`` (its scheduler starts in this
    process; no job is submitted until it is scaled)."""
    import dask_jobqueue

    cls = getattr(dask_jobqueue, JOBQUEUE_KINDS[config.kind])
    return cls(**config.cluster_kwargs())


def job_script(config: JobQueueConfig) -> str:
    """The batch script one job of ``config`` would be submitted with."""
    with jobqueue_cluster(config) as cluster:
        return cluster.job_script()


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


def worker_memory_budget(config: ClusterConfig | None) -> int | None:
    """Bytes one worker may use: ``memory_limit`` when given, else (``"auto"``)
    the machine's memory divided among the local workers; a batch job's
    memory divided among its worker processes; in-process (synchronous)
    runs the machine's memory; ``None`` for an existing cluster whose
    workers' limits were set elsewhere and not given."""
    import psutil
    from dask.utils import parse_bytes

    config = config or ClusterConfig()
    if config.jobqueue is not None:
        jq = config.jobqueue
        return int(parse_bytes(jq.memory) / (jq.processes or jq.cores))
    if config.memory_limit != "auto":
        return int(parse_bytes(config.memory_limit))
    if config.scheduler == "synchronous":
        return int(psutil.virtual_memory().total)
    if config.scheduler not in (None, "threads"):  # threads share this process: each task its share, as a worker's
        return None
    return int(psutil.virtual_memory().total / config.local_workers)


def tasks_per_device(config: ClusterConfig | None) -> int | None:
    """Matching tasks that may run at once on one GPU of a worker's
    machine: the local workers (threads or processes, one task each), a
    batch job's worker processes, one when synchronous; ``None`` for an
    existing cluster (its layout is not known here)."""
    config = config or ClusterConfig()
    if config.jobqueue is not None:
        return int(config.jobqueue.processes or config.jobqueue.cores)
    if config.scheduler == "synchronous":
        return 1
    if config.scheduler not in (None, "threads"):
        return None
    return int(config.local_workers)


@contextlib.contextmanager
def compute_context(config: ClusterConfig = ClusterConfig()) -> Iterator[object | None]:
    """Context in which ``dask.compute`` runs on the configured scheduler.

    Yields the :class:`distributed.Client` (or ``None`` when synchronous).
    A task that killed its worker every time it was tried (dask's
    ``KilledWorker``: the nanny stops a worker at its memory limit) ends
    the run with :class:`~tiledsm.errors.WorkerMemoryError`, naming the
    task and the limit, instead of a scheduler traceback.
    """
    try:
        with _compute_context(config) as client:
            yield client
    except Exception as exc:
        if type(exc).__name__ != "KilledWorker":
            raise
        from dask.utils import format_bytes

        from tiledsm.errors import WorkerMemoryError

        budget = worker_memory_budget(config)
        limit = f"{format_bytes(budget)} per worker" if budget else "the workers' own limit"
        raise WorkerMemoryError(
            f"a worker died each time it ran task {exc.args[0] if exc.args else '?'} (memory limit: {limit}); "
            "most likely it ran out of memory: use smaller chunks, fewer --workers, or a larger --memory-per-worker"
        ) from None


@contextlib.contextmanager
def _compute_context(config: ClusterConfig) -> Iterator[object | None]:
    if config.scheduler == "synchronous":
        with dask.config.set(scheduler="synchronous"):
            yield None
        return
    if config.scheduler == "threads":
        single_threaded_libraries()  # one thread per task, as in a worker process
        with dask.config.set(scheduler="threads", num_workers=config.local_workers):
            yield None
        return
    from distributed import Client, LocalCluster

    if config.jobqueue is not None:
        jq = config.jobqueue
        with jobqueue_cluster(jq) as cluster, Client(cluster) as client:
            cluster.adapt(minimum_jobs=jq.minimum_jobs, maximum_jobs=jq.maximum_jobs)
            yield client
        return
    if config.scheduler:
        with Client(config.scheduler) as client:
            client.run(single_threaded_libraries)
            yield client
        return
    n = config.local_workers
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
    its own); an explicit scheduler, ``"threads"`` or ``"synchronous"`` is yielded as is."""
    if config.scheduler is not None:
        yield config
        return
    import dataclasses

    with compute_context(config) as client:
        yield dataclasses.replace(config, scheduler=client.scheduler.address, jobqueue=None)


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
