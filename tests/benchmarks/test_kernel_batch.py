"""What a compiled EKF step costs against the batch: a fixed cost per step and one per trajectory.

Run with ``python -m pytest tests/benchmarks/test_kernel_batch.py --benchmark-only``.

The compiled EKF's two kernels, the generic one (``estimators/filters/kalman_kernels.py``) and the
unrolled one (``estimators/filters/kalman_unrolled.py``), side by side on 1000 samples of Duffing
and of Lorenz, at batches of 1 to 160 trajectories, one thread. Each records
``ns_per_trajectory_step`` in its ``extra_info``; a line through the per-step costs
``batch * ns_per_trajectory_step`` gives the fixed cost of a step (its loops' set-up over
the batch, whatever its size) and the cost of each trajectory in it (protocol 6.3 quotes
both beside the row's floor).
"""

import numpy as np
import pytest
from kkl_bench.estimators.filters import kalman_kernels, kalman_unrolled

from kkl_bench.registry import systems
from kkl_bench.support.executors import thread_limit

STEPS = 1000
BATCHES = (1, 5, 10, 20, 40, 80, 160)
KERNELS = {
    "generic": lambda model, arguments: kalman_kernels.ekf(*model.functions, *arguments),
    "unrolled": lambda model, arguments: kalman_unrolled.run_ekf(model, *arguments[4:]),
}


def _case(system: str, batch: int):
    model = systems.get(system)().compiled()
    rng = np.random.default_rng(0)
    y = 0.1 * rng.standard_normal((batch, STEPS, model.n_y))
    u = np.repeat(np.sin(0.05 * np.arange(STEPS))[None], batch, axis=0)
    n = model.n_x
    out = np.full((batch, STEPS, n), np.nan)
    return model, (
        model.p, model.q, model.s, model.g, y, u, 0.05,
        np.zeros(n), np.eye(n), 1e-3 * np.eye(n), 0.01 * np.eye(model.n_y), 1.0, np.inf, out,
    )  # fmt: skip


@pytest.mark.parametrize("batch", BATCHES)
@pytest.mark.parametrize("system", ["duffing", "lorenz"])
@pytest.mark.parametrize("kernel", KERNELS)
def test_ekf_kernel_against_batch(benchmark, kernel, system, batch):
    model, arguments = _case(system, batch)
    run = KERNELS[kernel]
    with thread_limit(1):
        run(model, arguments)  # compiled before timing
        assert np.isfinite(arguments[-1]).all()
        benchmark(run, model, arguments)
    benchmark.extra_info["ns_per_trajectory_step"] = (
        1e9 * benchmark.stats.stats.min / (batch * STEPS)
    )
