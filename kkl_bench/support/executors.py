"""One way to run independent jobs: an unordered joblib generator, on local processes or Dask.

``loky`` (the default) runs jobs in worker processes on this machine, each
limited to ``threads`` threads (BLAS, OpenMP and torch, through the environment
loky gives its workers; at most ``cores // jobs``) so that N workers do not
oversubscribe the cores; with one job it runs them in this process, limited
likewise. One thread a job is the default: the benchmark's networks and filters
are small, a second thread speeds a job up little, and two runs side by side on
the same cores, which cannot see each other, then never oversubscribe them.

``dask`` sends the same jobs through joblib's Dask backend to a ``distributed``
cluster: the scheduler at ``scheduler`` if given (which is how SLURM or PBS clusters
are reached, through dask-jobqueue), else a ``LocalCluster`` of ``jobs``
single-threaded worker processes. Results come back in completion order.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from joblib import Parallel, delayed, parallel_config
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
def _dask_client(jobs: int, scheduler: str | None) -> Iterator[None]:
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
        with parallel_config(backend="dask"):
            yield
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
) -> Iterator[Any]:
    """Yield ``function(*args)`` for every ``args`` in ``arguments``, in completion order,
    each job on :func:`threads_per_worker` threads (Dask workers: one).

    Raises ``ValueError`` for an unknown executor or a ``jobs`` below 1.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; valid executors: {', '.join(EXECUTORS)}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if executor == "dask":
        with _dask_client(jobs, scheduler):
            task = limited(function, 1)
            yield from Parallel(n_jobs=-1, return_as="generator_unordered")(
                delayed(task)(*args) for args in arguments
            )
        return
    if scheduler:
        raise ValueError("--scheduler is for the dask executor")
    per_job = threads_per_worker(jobs, threads)
    if jobs == 1:
        for args in arguments:
            with thread_limit(per_job):
                result = function(*args)
            yield result
        return
    # loky sets OMP/MKL/OpenBLAS thread counts in each worker's environment when
    # it starts them; torch reads them when (and only if) a job imports it
    with parallel_config(backend="loky", n_jobs=jobs, inner_max_num_threads=per_job):
        yield from Parallel(return_as="generator_unordered")(
            delayed(function)(*args) for args in arguments
        )
