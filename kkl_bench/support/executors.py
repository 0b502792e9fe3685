"""One way to run independent jobs, on local processes or Dask, results in completion order.

``loky`` (the default) runs jobs in worker processes on this machine (joblib's
reusable loky executor), each limited to ``threads`` threads (BLAS, OpenMP and torch,
through the environment its workers start with; at most ``cores // jobs``) so that N
workers do not oversubscribe the cores; with one job it runs them in this process,
limited likewise. One thread a job is the default: the benchmark's networks and
filters are small, a second thread speeds a job up little, and two runs side by side
on the same cores, which cannot see each other, then never oversubscribe them.

``dask`` sends the same jobs to a ``distributed`` cluster: the scheduler at
``scheduler`` if given (which is how SLURM or PBS clusters are reached, through
dask-jobqueue), else a ``LocalCluster`` of ``jobs`` single-threaded worker processes.

Either way jobs that would train the same model do not run at once
(:class:`Schedule`): the second would hold a worker, or a core, idle on the first's
lock for as long as the training lasts, while other jobs wait.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Collection, Hashable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from typing import Any

from joblib.externals.loky import get_reusable_executor
from threadpoolctl import threadpool_limits

EXECUTORS = ("loky", "dask")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. under ``taskset`` or a
    container's cpuset), not the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def threads_per_worker(jobs: int, threads: int | None = None) -> int:
    """Threads each of ``jobs`` concurrent workers uses: ``threads`` (default
    :data:`THREADS_PER_JOB`), at most its share of the cores this process has."""
    share = max(1, available_cores() // jobs)
    return min(share, THREADS_PER_JOB if threads is None else threads)


THREADS_PER_JOB = 1
"""Threads a job uses unless told otherwise (see the module)."""


@contextlib.contextmanager
def thread_limit(threads: int) -> Iterator[None]:
    """Limit BLAS/OpenMP and torch to ``threads`` inside the block; torch's own count is
    restored after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with threadpool_limits(limits=threads):
            yield
    finally:
        torch.set_num_threads(before)


def limited(function: Callable, threads: int) -> Callable:
    """``function`` run with BLAS/OpenMP and torch limited to ``threads`` (for Dask workers,
    whose environment this package does not set)."""

    def call(*args: Any) -> Any:
        with thread_limit(threads):
            return function(*args)

    return call


@contextlib.contextmanager
def _dask_client(jobs: int, scheduler: str | None) -> Iterator[Any]:
    """A ``distributed`` client of the scheduler at ``scheduler``, else of a local cluster
    of ``jobs`` single-threaded worker processes (closed after the block)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as error:
        raise ValueError("the dask executor needs `pip install 'kkl-bench[dask]'`") from error
    if scheduler:
        client = Client(scheduler)
        cluster = None
    else:
        cluster = LocalCluster(
            n_workers=jobs,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        )
        client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def execute(
    function: Callable,
    arguments: Iterable[tuple],
    jobs: int = 1,
    executor: str = "loky",
    scheduler: str | None = None,
    threads: int | None = None,
    claims: Sequence[Collection[Hashable]] | None = None,
) -> Iterator[Any]:
    """Yield ``function(*args)`` for every ``args`` in ``arguments``, in completion order,
    each job on :func:`threads_per_worker` threads (Dask workers: one).

    Jobs start in the order given as workers free up, except that a job is held back
    while a running job shares one of its ``claims`` (one collection of names per job;
    default none) that no finished job has held: the name of a model both would train,
    which one trains while the other would only wait for its lock, and the first to
    finish has saved for the others (:class:`Schedule`). Local processes run ``jobs``
    at once; Dask gets every job that may start and runs them as its workers free up.

    Raises ``ValueError`` for an unknown executor, a ``jobs`` below 1, or ``claims`` not
    one per job.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; valid executors: {', '.join(EXECUTORS)}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if scheduler and executor != "dask":
        raise ValueError("--scheduler is for the dask executor")
    arguments = list(arguments)
    if claims is not None and len(claims) != len(arguments):
        raise ValueError(f"claims must be one per job: {len(claims)} for {len(arguments)} jobs")
    schedule = Schedule([frozenset(names) for names in claims or [()] * len(arguments)])
    if executor == "dask":
        with _dask_client(jobs, scheduler) as client:
            pool = client.get_executor(pure=False)
            yield from _dispatch(pool, limited(function, 1), arguments, schedule, None)
        return
    per_job = threads_per_worker(jobs, threads)
    if jobs == 1:
        for args in arguments:
            with thread_limit(per_job):
                result = function(*args)
            yield result
        return
    # each worker's BLAS/OpenMP pools read these when they start; torch, imported by a
    # job, reads them too (and :func:`limited` sets its count again)
    env = {variable: str(per_job) for variable in THREAD_VARIABLES}
    pool = get_reusable_executor(max_workers=jobs, env=env)
    try:
        yield from _dispatch(pool, limited(function, per_job), arguments, schedule, jobs)
    except BaseException:  # a failed or interrupted run: stop the jobs still running
        pool.shutdown(wait=False, kill_workers=True)
        raise


THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMBA_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
"""The environment variables that limit a worker's thread pools (joblib's list)."""


class Schedule:
    """Which job starts next under claims (see :func:`execute`).

    ``claims[i]`` are job ``i``'s names. :meth:`start` takes the first job waiting,
    in the order given, none of whose names a running job holds, unless a finished job
    has held that name (it is :attr:`released`); :meth:`finish` ends a job and releases
    its names.
    """

    def __init__(self, claims: Sequence[frozenset]) -> None:
        self.claims = claims
        self.waiting = list(range(len(claims)))
        self.running: set[int] = set()
        self.released: set[Hashable] = set()

    def start(self) -> int | None:
        """The index of the job to start now, or None if every waiting job is held back
        (or none waits)."""
        held = set().union(*(self.claims[index] for index in self.running)) - self.released
        for position, index in enumerate(self.waiting):
            if not self.claims[index] & held:
                del self.waiting[position]
                self.running.add(index)
                return index
        return None

    def finish(self, index: int) -> None:
        self.running.remove(index)
        self.released |= self.claims[index]


def _dispatch(
    pool: Executor,
    function: Callable,
    arguments: list[tuple],
    schedule: Schedule,
    limit: int | None,
) -> Iterator[Any]:
    """Run the jobs on ``pool`` as ``schedule`` allows, at most ``limit`` at once (None:
    no limit), yielding their results as they finish; a job that raised raises here."""
    running: dict[Future, int] = {}
    try:
        while True:
            while limit is None or len(running) < limit:
                index = schedule.start()
                if index is None:
                    break
                running[pool.submit(function, *arguments[index])] = index
            if not running:
                return
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                schedule.finish(running.pop(future))
                yield future.result()
    finally:
        for future in running:
            future.cancel()
