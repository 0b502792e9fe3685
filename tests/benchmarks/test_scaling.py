"""Online cost against the state dimension: every estimator on Lorenz-96, n = 5 to 40.

The repeatable part of the scaling study (``kkl-bench scaling``): networks of
the standard profile's sizes, trained for a few steps only, timed on the
first 200 samples of the ``more-systems`` sinusoid test trajectories on one
thread. Run with ``python -m pytest tests/benchmarks/test_scaling.py
--benchmark-only``; each benchmark records ``us_per_trajectory_step`` in its
``extra_info``; compare rows of one run.
"""

import dataclasses
from pathlib import Path

import pytest

from kkl_bench import variants
from kkl_bench.analysis import scaling
from kkl_bench.registry import estimators
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import Task, get_profile, make_test_set
from tests.benchmarks.test_estimate_cost import SMALL_FIT, one_thread  # noqa: F401 (fixture)

NAMES = estimators.names()


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    cache = Path(tmp_path_factory.mktemp("cache"))
    models = {}
    for n in scaling.SIZES:
        system = scaling.system_name(n)
        spec = RunSpec(
            ("ekf",),
            (system,),
            (scaling.REGIME,),
            get_profile("standard"),
            cache_dir=cache,
            tracks=(scaling.TRACK,),
        )
        for name in NAMES:
            context = make_fit_context(spec, name, system, 0)
            context = dataclasses.replace(context, budget={**context.budget, **SMALL_FIT})
            models[name, n] = variants.build(name).fit(context)
    return models


@pytest.mark.parametrize("batch", scaling.BATCHES)
@pytest.mark.parametrize("n", scaling.SIZES)
@pytest.mark.parametrize("name", NAMES)
def test_estimate_scaling(benchmark, fitted, name, n, batch):
    benchmark.group = f"Lorenz-96 n = {n}, {batch} trajectories"
    data = make_test_set(Task(scaling.system_name(n), scaling.REGIME, 1, scaling.TRACK), 20).data
    t, y, u = (
        data.t[: scaling.STEPS],
        data.y[:batch, : scaling.STEPS],
        data.u[:batch, : scaling.STEPS],
    )
    estimate = benchmark.pedantic(fitted[name, n].estimate, (t, y, u), rounds=3, iterations=1)
    benchmark.extra_info["us_per_trajectory_step"] = (
        benchmark.stats.stats.min / (batch * len(t)) * 1e6
    )
    assert estimate.shape == (batch, len(t), n)
