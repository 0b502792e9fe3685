"""The compiled EKF on Lorenz-96, n = 5 to 160: the batch-last kernel against the large-system one.

Run with ``python -m pytest tests/benchmarks/test_large_ekf.py --benchmark-only``.

The generic kernel (``estimators/kalman_kernels.py``, the batch on the last axis of every
matrix, dense products) and the one-trajectory-at-a-time kernel with sparse factors and
BLAS products (``estimators/kalman_large.py``), side by side on 100 samples at batches 1
and 20, one thread. The generic kernel runs to n = 40 only: its ``2 n^3``-flop products in
batch-last loops take minutes a call beyond. Each benchmark records
``us_per_trajectory_step`` and, from the ``ekf`` row's own count, ``flops_per_trajectory_step``
in its ``extra_info``.
"""

import numpy as np
import pytest
from kkl_bench.estimators import kalman_kernels, kalman_large
from kkl_bench.systems.lorenz96 import SIZES, lorenz96

from kkl_bench.executors import thread_limit

STEPS = 100
KERNELS = {"generic": kalman_kernels.ekf, "large": kalman_large.ekf}
GENERIC_SIZES = (5, 10, 20, 40)


def _case(n: int, batch: int):
    model = lorenz96(n)().compiled()
    rng = np.random.default_rng(0)
    y = 8.0 + rng.standard_normal((batch, STEPS, model.n_y))
    u = np.repeat(np.sin(0.05 * np.arange(STEPS))[None], batch, axis=0)
    out = np.full((batch, STEPS, n), np.nan)
    return model, (
        model.p, model.q, model.s, model.g, y, u, 0.01,
        np.full(n, 8.0), np.eye(n), 1e-4 * np.eye(n), 0.01 * np.eye(model.n_y), 1.0, np.inf,
        out,
    )  # fmt: skip


@pytest.mark.parametrize("batch", (1, 20))
@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("kernel", KERNELS)
def test_lorenz96_ekf_kernel(benchmark, kernel, n, batch):
    if kernel == "generic" and n not in GENERIC_SIZES:
        pytest.skip(f"the generic kernel at n = {n}: minutes a call")
    model, arguments = _case(n, batch)
    run = KERNELS[kernel]
    with thread_limit(1):
        run(*model.functions, *arguments)  # compiled before timing
        assert np.isfinite(arguments[-1]).all()
        benchmark.pedantic(run, (*model.functions, *arguments), rounds=3, iterations=1)
    benchmark.group = f"Lorenz-96 EKF, n = {n}, batch {batch}"
    benchmark.extra_info["us_per_trajectory_step"] = (
        1e6 * benchmark.stats.stats.min / (batch * STEPS)
    )
    if kernel == "large":
        nonzeros = kalman_large.structural_nonzeros(model)
        flops = kalman_large.flops_per_step(model, nonzeros, robust=False)
        benchmark.extra_info["flops_per_trajectory_step"] = flops
