"""What a hard-track limit cell costs at 40000 particles, on each particle-filter engine.

Run with ``python -m pytest tests/benchmarks/test_limit_cost.py --benchmark-only``.

``particle_filter[n=40000]`` (the count protocol 6.1's particle-count check reaches) on
the first :data:`TRAJECTORIES` test trajectories of the standard profile's Rossler
``outliers-square`` cell (the outlier law's mixture proposal, the dearest the track
has), one thread, once per engine. Each records ``us_per_trajectory_step`` and
``cell_minutes``: what the cell's 20 trajectories take at that rate.
"""

import numpy as np
import pytest

from kkl_bench import variants
from kkl_bench.run.spec import RunSpec, fit_context_for_row
from kkl_bench.suite.task import Task, get_profile, make_test_set
from kkl_bench.support.executors import thread_limit

TASK = Task("rossler", "outliers-square", track="hard")
TRAJECTORIES = 2


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_limit_cell_at_40000_particles(benchmark, engine, tmp_path):
    profile = get_profile("standard")
    row = variants.canonical(f"particle_filter[engine={engine!r},n=40000]")
    spec = RunSpec((row,), (TASK.system,), None, profile, cache_dir=tmp_path, tracks=("hard",))
    estimator = variants.build(row).fit(fit_context_for_row(spec, row, TASK.system, [TASK], 0))
    data = make_test_set(TASK, profile.n_test).data
    t, y, u = data.t, data.y[:TRAJECTORIES], data.u[:TRAJECTORIES]
    with thread_limit(1):
        estimator.estimate(t[:2], y[:, :2], u[:, :2])  # compiled before timing
        estimate = benchmark.pedantic(estimator.estimate, (t, y, u), rounds=1, iterations=1)
    assert np.isfinite(estimate).all()
    us = 1e6 * benchmark.stats.stats.min / (TRAJECTORIES * len(t))
    benchmark.extra_info["us_per_trajectory_step"] = us
    benchmark.extra_info["cell_minutes"] = us * profile.n_test * len(t) / 6e7
