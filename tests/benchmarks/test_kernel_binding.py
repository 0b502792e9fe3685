"""What compiling the particle filter's kernel once for every model saves and costs.

Run with ``python -m pytest tests/benchmarks/test_kernel_binding.py --benchmark-only``.

The kernel bound once (:func:`kkl_bench.support.kernel_cache.bind_once`, the model's
functions as first-class values) against the kernel bound to each model
(:func:`kkl_bench.support.kernel_cache.bind`), one thread:

- ``test_a_second_system_from_empty_caches``: a fresh process with empty caches estimates
  on Duffing, then on Van der Pol; ``second_system_s`` is the second estimate's time, its
  compilation included (the kernel again for ``bind``, only Van der Pol's functions for
  ``bind_once``).
- ``test_estimate``: a row's estimate of a quick sinusoid cell's 5 test trajectories with
  each binding in turn, its kernels compiled before timing: what the indirect calls
  cost. The board's ``particle_filter`` (10000 particles) on Duffing, which binds once;
  the compiled EKF and UKF on Chua (three states, the generic kernels: its drift does
  not trace) and the EKF on Lorenz-96 n = 20, which keep a kernel per model.
"""

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from kkl_bench.estimators.filters import ekf, particle_filter, ukf

from kkl_bench import variants
from kkl_bench.run.spec import RunSpec, fit_context_for_row
from kkl_bench.suite.task import Task, get_profile, make_test_set
from kkl_bench.support import kernel_cache
from kkl_bench.support.executors import thread_limit

BINDINGS = ("bind", "bind_once")

TWO_SYSTEMS = """
import sys, time
from kkl_bench import variants
from kkl_bench.estimators.filters import particle_filter
from kkl_bench.run.spec import RunSpec, fit_context_for_row
from kkl_bench.suite.task import Task, get_profile, make_test_set
from kkl_bench.support import kernel_cache

particle_filter.bind_once = getattr(kernel_cache, sys.argv[1])
profile = get_profile("quick")
for system in ("duffing", "vdp"):
    task = Task(system, "sinusoid")
    spec = RunSpec(("particle_filter[n=100]",), (system,), None, profile, cache_dir=sys.argv[2])
    context = fit_context_for_row(spec, "particle_filter[n=100]", system, [task], 0)
    estimator = variants.build("particle_filter[n=100]").fit(context)
    data = make_test_set(task, profile.n_test).data
    start = time.perf_counter()
    estimator.estimate(data.t, data.y, data.u)
print(time.perf_counter() - start)
"""


@pytest.mark.parametrize("binding", BINDINGS)
def test_a_second_system_from_empty_caches(benchmark, binding, tmp_path):
    environment = os.environ | {
        "KKL_BENCH_CACHE": str(tmp_path / "cache"),
        "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
        "OMP_NUM_THREADS": "1",
    }

    def run() -> str:
        command = [sys.executable, "-c", TWO_SYSTEMS, binding, str(tmp_path / "models")]
        done = subprocess.run(command, env=environment, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout

    benchmark.extra_info["second_system_s"] = float(benchmark.pedantic(run, rounds=1, iterations=1))


ROWS = {  # row: (its module, the binding it calls, the system, the track)
    "particle_filter": (particle_filter, "bind_once", "duffing", "paper"),
    "ekf[engine='compiled']": (ekf, "bind", "chua", "more-systems"),
    "ukf[engine='compiled']": (ukf, "bind", "chua", "more-systems"),
    "ekf[engine='compiled'] n=20": (ekf, "bind", "lorenz96-n20", "more-systems"),
}


@pytest.mark.parametrize("case", ROWS)
def test_estimate(benchmark, case, tmp_path, monkeypatch):
    """Each round estimates once per binding, in turn: ``extra_info`` has each one's median
    seconds and ``bind_once_over_bind``, the ratio of the medians."""
    module, called, system, track = ROWS[case]
    row = case.partition(" ")[0]
    task, profile = Task(system, "sinusoid", track=track), get_profile("quick")
    spec = RunSpec((row,), (system,), None, profile, cache_dir=tmp_path, tracks=(track,))
    estimator = variants.build(row).fit(fit_context_for_row(spec, row, system, [task], 0))
    data = make_test_set(task, profile.n_test).data
    seconds = {binding: [] for binding in BINDINGS}

    def both():
        for binding in BINDINGS:
            monkeypatch.setattr(module, called, getattr(kernel_cache, binding))
            start = time.perf_counter()
            estimate = estimator.estimate(data.t, data.y, data.u)
            seconds[binding].append(time.perf_counter() - start)
            assert np.isfinite(estimate).all()

    with thread_limit(1):
        both()  # compiled before timing
        for times in seconds.values():
            times.clear()
        benchmark.pedantic(both, rounds=7, iterations=1)
    medians = {binding: float(np.median(times)) for binding, times in seconds.items()}
    benchmark.extra_info.update(medians)
    benchmark.extra_info["bind_once_over_bind"] = medians["bind_once"] / medians["bind"]
