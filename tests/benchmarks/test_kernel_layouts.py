"""What the compiled engines' layout costs: one RK4 step of Duffing for 40000 points, two ways.

Run with ``python -m pytest tests/benchmarks/test_kernel_layouts.py --benchmark-only``.

- ``swept``: the compiled engines' design (``kkl_bench.protocol.compiled.rk4_step`` over
  the system's ``drift``, each operation swept over all points at once, ``x: (n_x, m)``);
- ``scalar``: the step written out in scalars (what the arithmetic allows).

Each records ``ns_per_point`` in its ``extra_info``; divide two rows of one run for a
ratio (protocol 6.3 quotes them). One thread, as each worker of ``kkl-bench run``.
"""

import numba
import numpy as np
import pytest

from kkl_bench.protocol.compiled import rk4_step
from kkl_bench.registry import systems
from kkl_bench.support.executors import thread_limit

POINTS = 40000
DT = 0.05


@numba.njit
def _swept(drift, p, g, points, u, dt, out):
    rk4_step(
        drift, p, g, points, np.full(points.shape[1], u), dt, out, np.empty((5, *points.shape))
    )


@numba.njit
def _scalar(a, g, points, u, dt, out):
    g0, g1 = g[0] * u, g[1] * u
    for j in range(points.shape[1]):
        x0, x1 = points[0, j], points[1, j]
        k10, k11 = a * x1 * x1 * x1 + g0, -x0 + g1
        s0, s1 = x0 + 0.5 * dt * k10, x1 + 0.5 * dt * k11
        k20, k21 = a * s1 * s1 * s1 + g0, -s0 + g1
        s0, s1 = x0 + 0.5 * dt * k20, x1 + 0.5 * dt * k21
        k30, k31 = a * s1 * s1 * s1 + g0, -s0 + g1
        s0, s1 = x0 + dt * k30, x1 + dt * k31
        k40, k41 = a * s1 * s1 * s1 + g0, -s0 + g1
        out[0, j] = x0 + dt / 6.0 * (k10 + 2.0 * k20 + 2.0 * k30 + k40)
        out[1, j] = x1 + dt / 6.0 * (k11 + 2.0 * k21 + 2.0 * k31 + k41)


@pytest.fixture(scope="module")
def case():
    model = systems.get("duffing")().compiled()
    points = np.random.default_rng(0).uniform(-1.0, 1.0, (model.n_x, POINTS))
    return model, points


LAYOUTS = {
    "swept": lambda m, x, u, out: _swept(m.drift, m.p, m.g, x, u, DT, out),
    "scalar": lambda m, x, u, out: _scalar(m.p[0], m.g, x, u, DT, out),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_rk4_step_layout(benchmark, case, layout):
    model, points = case
    out = np.empty_like(points)
    reference = np.empty_like(points)
    _swept(model.drift, model.p, model.g, points, 0.3, DT, reference)
    with thread_limit(1):
        LAYOUTS[layout](model, points, 0.3, out)  # compiled before timing
        np.testing.assert_allclose(out, reference, rtol=1e-12, atol=1e-14)
        benchmark(LAYOUTS[layout], model, points, 0.3, out)
    benchmark.extra_info["ns_per_point"] = 1e9 * benchmark.stats.stats.min / POINTS
