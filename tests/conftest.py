import os

import pytest

from kkl_bench.executors import threads_per_worker
from kkl_bench.registry import estimators


def pytest_configure(config):
    """Under pytest-xdist (``-n``), each worker and the commands it starts get an equal
    share of the cores, instead of every worker's torch and BLAS taking all of them."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        import torch

        threads = threads_per_worker(int(workers))
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(threads)
        torch.set_num_threads(threads)


@pytest.fixture
def register_estimator(monkeypatch):
    """Register an estimator class under a name for one test only."""

    def register(name, cls):
        monkeypatch.setitem(estimators._loaded, name, cls)
        return cls

    return register
