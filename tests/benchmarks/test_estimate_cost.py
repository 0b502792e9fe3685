"""Online cost of every estimator's ``estimate``, side by side on one cell of each paper system.

Run with ``python -m pytest tests/benchmarks --benchmark-only`` (``-k="-1]"``: one
trajectory; ``-k="duffing-ekf-"``: the EKF on Duffing). Networks have
the standard profile's sizes (what costs time online) but are trained for a
few steps only (what they estimate does not matter here). Each benchmark
records ``us_per_trajectory_step``, ``flops_per_trajectory_step`` (counted as
``kkl-bench cost`` counts them) and ``over_floor`` in its ``extra_info``; divide two rows of
one run for a ratio (the machine is shared, absolute times drift). Everything
runs on one thread, as each worker of ``kkl-bench run --jobs 2`` does on a
2-core machine.
"""

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from kkl_bench import variants
from kkl_bench.analysis import cost
from kkl_bench.analysis.findings import PAPER_SYSTEMS
from kkl_bench.registry import estimators, systems
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import Task, get_profile, make_test_set
from kkl_bench.support.executors import thread_limit

SYSTEMS, REGIME = PAPER_SYSTEMS, "sinusoid"
SMALL_FIT = {
    "train_trajectories": 16,
    "encoder_steps": 50,
    "decoder_steps": 50,
    "selection_steps": 20,
    "phase2_trajectories": 8,
    "phase2_steps": 20,
    "adaptation_steps": 20,
    "adaptation_trajectories": 8,
    "curriculum_epoch_steps": 10,
    "max_epochs": 2,
    "rnn_trajectories": 8,
    "rnn_validation": 2,
    "rnn_steps": 20,
}
"""The budget cut for the timings: the models keep the profile's sizes, so the arithmetic
timed is the published rows'; how well they trained does not enter an estimate's cost. Not
:data:`tests.budgets.FEW_STEPS`: these are the cuts the committed timings were made with."""
LEARNED = sorted(set(estimators.names()) - {"ekf", "ukf"})
COMPILED = [f"{name}[engine='compiled']" for name in ("ekf", "ukf", "enkf", "particle_filter")]
"""The filters' compiled engines, timed beside their reference engines (the rows above)."""
ROWS = ["ekf", "ukf", *LEARNED, *COMPILED]
BATCHES = {"ekf": (1, 20), "ukf": (1, 20), "particle_filter": (1, 20)}
"""Trajectories per call; the filters' loops are too slow for 1000 (the others: 1, 20, 1000;
the particle filter's 1000 would take about 30 minutes)."""


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    with thread_limit(1):
        yield


@pytest.fixture(scope="module", params=SYSTEMS)
def system(request):
    return request.param


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, system):
    cache = tmp_path_factory.mktemp("cache")
    spec = RunSpec(("ekf",), (system,), (REGIME,), get_profile("standard"), cache_dir=Path(cache))
    fitted = {}
    for name in ROWS:
        context = make_fit_context(spec, name, system, 0)
        context = dataclasses.replace(context, budget={**context.budget, **SMALL_FIT})
        estimator = variants.build(name)
        reason = estimator.unsupported_reason(context.system, context.measurement)
        fitted[name] = reason or estimator.fit(context)  # a row that cannot run here: why
    return fitted


@pytest.fixture(scope="module")
def peaks():
    """This machine's peak GFLOP/s on one thread, per precision (protocol 6.3)."""
    return {precision: cost.peak_gflops(precision) for precision in ("float32", "float64")}


def batch_of(system: str, n: int):
    """``(t, y, u)`` of ``n`` trajectories: the cell's 20 test trajectories, repeated."""
    data = make_test_set(Task(system, REGIME), 20).data
    rows = np.arange(n) % 20
    return data.t, data.y[rows], data.u[rows]


@pytest.mark.parametrize(
    ("name", "batch"),
    [
        (name, batch)
        for name in ROWS
        for batch in BATCHES.get(variants.parse(name)[0], (1, 20, 1000))
    ],
)
def test_estimate(benchmark, system, fitted, peaks, name, batch):
    if isinstance(fitted[name], str):
        pytest.skip(f"{name} on {system}: {fitted[name]}")
    benchmark.group = f"estimate on {system}, {batch} trajectories"
    t, y, u = batch_of(system, batch)
    estimate = benchmark.pedantic(
        fitted[name].estimate, (t, y, u), rounds=3 if batch < 1000 else 1, iterations=1
    )
    us = benchmark.stats.stats.min / (batch * len(t)) * 1e6
    flops, precision = cost.counted_flops(fitted[name], SimpleNamespace(t=t, y=y, u=u))
    benchmark.extra_info["us_per_trajectory_step"] = us
    benchmark.extra_info["flops_per_trajectory_step"] = flops
    benchmark.extra_info["over_floor"] = us / (flops / (peaks[precision] * 1e3))
    assert estimate.shape == (batch, len(t), systems.get(system)().n_x)


@pytest.mark.parametrize("rows", [20, 1000])
def test_float32_matrix_product_throughput(benchmark, rows):
    """The floor under every network's online cost: one thread's float32 product of a
    ``(rows, 128)`` block with a ``128 x 128`` weight (a hidden layer of the chaotic
    systems' networks at the standard batch and at 1000 trajectories), in GFLOP/s."""
    rng = np.random.default_rng(0)
    block = rng.standard_normal((rows, 128), dtype=np.float32)
    weight = rng.standard_normal((128, 128), dtype=np.float32)
    product = np.empty((rows, 128), dtype=np.float32)
    benchmark.group = "float32 matrix product"
    benchmark(np.matmul, block, weight, out=product)
    benchmark.extra_info["gflop_per_s"] = 2 * rows * 128 * 128 / benchmark.stats.stats.min / 1e9
    np.testing.assert_allclose(product, block @ weight, rtol=1e-5, atol=1e-3)
