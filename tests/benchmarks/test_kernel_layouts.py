"""What the compiled engines' layout costs: one RK4 step of Duffing for 40000 points, three ways.

Run with ``python -m pytest tests/benchmarks/test_kernel_layouts.py --benchmark-only``.

- ``per_point``: the compiled engines' design (``kkl_bench.protocol.compiled.rk4_step``
  over the system's ``drift`` of one state vector, called point after point);
- ``swept``: the same operations, each swept over an array of points (a drift of many
  points, as a vectorized kernel would take it);
- ``scalar``: the step written out in scalars (what the arithmetic allows).

Each records ``ns_per_point`` in its ``extra_info``; divide two rows of one run for a
ratio (protocol 6.3 quotes them). One thread, as each worker of ``kkl-bench run``.
"""

import numba
import numpy as np
import pytest

from kkl_bench.executors import thread_limit
from kkl_bench.protocol.compiled import rk4_step
from kkl_bench.registry import systems

POINTS = 40000
DT = 0.05


@numba.njit
def _per_point(drift, p, g, points, u, dt, out):
    n = points.shape[1]
    mean, work = np.empty(n), np.empty((5, n))
    for j in range(points.shape[0]):
        rk4_step(drift, p, g, points[j], u, dt, mean, work)
        out[j] = mean


@numba.njit
def _duffing_drift_swept(x, a, out):
    for j in range(x.shape[0]):
        x2 = x[j, 1]
        out[j, 0] = a * x2 * x2 * x2
        out[j, 1] = -x[j, 0]


@numba.njit
def _stage(x, k, g, u, scale, out):
    """``out = x + scale (k + g u)`` over every point (``k`` the drift there)."""
    for j in range(x.shape[0]):
        for i in range(x.shape[1]):
            out[j, i] = x[j, i] + scale * (k[j, i] + u * g[i])


@numba.njit
def _swept(a, g, points, u, dt, out):
    m, n = points.shape
    k = np.empty((4, m, n))
    stage = np.empty((m, n))
    _duffing_drift_swept(points, a, k[0])
    _stage(points, k[0], g, u, 0.5 * dt, stage)
    _duffing_drift_swept(stage, a, k[1])
    _stage(points, k[1], g, u, 0.5 * dt, stage)
    _duffing_drift_swept(stage, a, k[2])
    _stage(points, k[2], g, u, dt, stage)
    _duffing_drift_swept(stage, a, k[3])
    sixth = dt / 6.0
    for j in range(m):
        for i in range(n):
            total = k[0, j, i] + 2.0 * k[1, j, i] + 2.0 * k[2, j, i] + k[3, j, i]
            out[j, i] = points[j, i] + sixth * (total + 6.0 * u * g[i])


@numba.njit
def _scalar(a, g, points, u, dt, out):
    g0, g1 = g[0] * u, g[1] * u
    for j in range(points.shape[0]):
        x0, x1 = points[j, 0], points[j, 1]
        k10, k11 = a * x1 * x1 * x1 + g0, -x0 + g1
        s0, s1 = x0 + 0.5 * dt * k10, x1 + 0.5 * dt * k11
        k20, k21 = a * s1 * s1 * s1 + g0, -s0 + g1
        s0, s1 = x0 + 0.5 * dt * k20, x1 + 0.5 * dt * k21
        k30, k31 = a * s1 * s1 * s1 + g0, -s0 + g1
        s0, s1 = x0 + dt * k30, x1 + dt * k31
        k40, k41 = a * s1 * s1 * s1 + g0, -s0 + g1
        out[j, 0] = x0 + dt / 6.0 * (k10 + 2.0 * k20 + 2.0 * k30 + k40)
        out[j, 1] = x1 + dt / 6.0 * (k11 + 2.0 * k21 + 2.0 * k31 + k41)


@pytest.fixture(scope="module")
def case():
    model = systems.get("duffing")().compiled()
    points = np.random.default_rng(0).uniform(-1.0, 1.0, (POINTS, model.n_x))
    return model, points


LAYOUTS = {
    "per_point": lambda m, x, u, out: _per_point(m.drift, m.p, m.g, x, u, DT, out),
    "swept": lambda m, x, u, out: _swept(m.p[0], m.g, x, u, DT, out),
    "scalar": lambda m, x, u, out: _scalar(m.p[0], m.g, x, u, DT, out),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_rk4_step_layout(benchmark, case, layout):
    model, points = case
    out = np.empty_like(points)
    reference = np.empty_like(points)
    _per_point(model.drift, model.p, model.g, points, 0.3, DT, reference)
    with thread_limit(1):
        LAYOUTS[layout](model, points, 0.3, out)  # compiled before timing
        np.testing.assert_allclose(out, reference, rtol=1e-12, atol=1e-14)
        benchmark(LAYOUTS[layout], model, points, 0.3, out)
    benchmark.extra_info["ns_per_point"] = 1e9 * benchmark.stats.stats.min / POINTS
