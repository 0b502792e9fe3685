"""The compiled EKF and UKF on Lorenz-96, n = 5 to 160: the batch-last kernels against the
large-system ones.

Run with ``python -m pytest tests/benchmarks/test_large_filters.py --benchmark-only``.

The generic kernels (``estimators/filters/kalman_kernels.py``, the batch on the last axis of every
matrix, dense loops) and the one-trajectory-at-a-time kernels with BLAS products
(``estimators/filters/kalman_large.py``: the EKF's sparse factors by their nonzeros, the UKF's sigma
points as the columns the model sweeps), side by side on 100 samples at batches 1 and 20,
one thread. The generic kernels run to n = 40 (the EKF) and 80 (the UKF) only: beyond, a
call takes minutes. Each benchmark records ``us_per_trajectory_step`` and, for the EKF's
large kernel, from the ``ekf`` row's own count, ``flops_per_trajectory_step`` in its
``extra_info``.
"""

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from kkl_bench.estimators.filters import kalman_kernels, kalman_large
from kkl_bench.systems.lorenz96 import SIZES, lorenz96

from kkl_bench.support.executors import thread_limit

STEPS = 100
KERNELS = {
    ("ekf", "generic"): kalman_kernels.ekf,
    ("ekf", "large"): kalman_large.ekf,
    ("ukf", "generic"): kalman_kernels.ukf,
    ("ukf", "large"): kalman_large.ukf,
}
GENERIC_SIZES = {"ekf": (5, 10, 20, 40), "ukf": (5, 10, 20, 40, 80)}


def _case(name: str, n: int, batch: int):
    model = lorenz96(n)().compiled()
    rng = np.random.default_rng(0)
    y = 8.0 + rng.standard_normal((batch, STEPS, model.n_y))
    u = np.repeat(np.sin(0.05 * np.arange(STEPS))[None], batch, axis=0)
    out = np.full((batch, STEPS, n), np.nan)
    noise = (np.full(n, 8.0), np.eye(n), 1e-4 * np.eye(n), 0.01 * np.eye(model.n_y))
    sigma = ()
    if name == "ukf":  # the row's default sigma points (alpha 0.5, beta 2, kappa 0)
        points = MerweScaledSigmaPoints(n, alpha=0.5, beta=2.0, kappa=0.0)
        sigma = (points.Wm, points.Wc, points.alpha**2 * n)
    return model, (
        model.p, model.q, model.s, model.g, y, u, 0.01, *noise, *sigma, 1.0, np.inf, out,
    )  # fmt: skip


@pytest.mark.parametrize("batch", (1, 20))
@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize(("name", "kernel"), KERNELS)
def test_lorenz96_filter_kernel(benchmark, name, kernel, n, batch):
    if kernel == "generic" and n not in GENERIC_SIZES[name]:
        pytest.skip(f"the generic {name} kernel at n = {n}: minutes a call")
    model, arguments = _case(name, n, batch)
    run = KERNELS[name, kernel]
    with thread_limit(1):
        run(*model.functions, *arguments)  # compiled before timing
        assert np.isfinite(arguments[-1]).all()
        benchmark.pedantic(run, (*model.functions, *arguments), rounds=3, iterations=1)
    benchmark.group = f"Lorenz-96 {name.upper()}, n = {n}, batch {batch}"
    benchmark.extra_info["us_per_trajectory_step"] = (
        1e6 * benchmark.stats.stats.min / (batch * STEPS)
    )
    if (name, kernel) == ("ekf", "large"):
        nonzeros = kalman_large.structural_nonzeros(model)
        flops = kalman_large.flops_per_step(model, nonzeros, robust=False)
        benchmark.extra_info["flops_per_trajectory_step"] = flops
