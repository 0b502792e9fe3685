"""Speed of test-set generation: the batched simulator against scipy, trajectory by trajectory.

Run with ``pytest tests/benchmarks --benchmark-only``; compare the
``standard_duffing_sinusoid`` rows of the two groups for the ratio.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from kkl_bench.registry import systems
from kkl_bench.suite.task import Task, build_test_set

ALL_CELLS = [
    Task(s, r)
    for s in ("duffing", "vdp", "rossler", "lorenz")
    for r in ("zero", "constant", "sinusoid", "square")
]


def test_all_sixteen_standard_test_sets(benchmark):
    benchmark.group = "test sets"
    test_sets = benchmark.pedantic(
        lambda: [build_test_set(task, 20) for task in ALL_CELLS], rounds=5, iterations=1
    )
    assert all(np.isfinite(t.data.x).all() for t in test_sets)


def test_standard_duffing_sinusoid_batched(benchmark):
    benchmark.group = "one cell, 20 trajectories"
    benchmark.pedantic(
        lambda: build_test_set(Task("duffing", "sinusoid"), 20), rounds=5, iterations=1
    )


def solve_ivp_trajectory_by_trajectory(test_set):
    """The same trajectories with scipy (RK45, rtol 1e-6), one held-input interval at a time."""
    system = systems.get(test_set.task.system)()
    data = test_set.data
    process_noise = np.diff(data.x, axis=1)  # only its shape matters for the work done
    for b in range(len(data)):
        x = data.x[b, 0].copy()
        for k in range(data.x.shape[1] - 1):
            x = (
                solve_ivp(
                    lambda _, state, uk=data.u[b, k, 0]: system.vector_field(state, np.asarray(uk)),
                    (0.0, 0.05),
                    x,
                    rtol=1e-6,
                ).y[:, -1]
                + 0.0 * process_noise[b, k]
            )


@pytest.fixture(scope="module")
def duffing_sinusoid():
    return build_test_set(Task("duffing", "sinusoid"), 20)


def test_standard_duffing_sinusoid_scipy(benchmark, duffing_sinusoid):
    benchmark.group = "one cell, 20 trajectories"
    benchmark.pedantic(
        lambda: solve_ivp_trajectory_by_trajectory(duffing_sinusoid), rounds=1, iterations=1
    )
