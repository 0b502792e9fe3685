"""Is an untrained model as costly online as the trained one? (``kkl-bench scaling --untrained``)

The scaling study may time models built at the profile's sizes with their trainings cut
short (:func:`kkl_bench.analysis.scaling_timing.fit_untrained`) instead of the trained models of a cache
(protocol section 8). This benchmark times both side by side, round-robin on one thread,
for the learned rows whose trained models the cache ``$KKL_BENCH_TRAINED_CACHE`` holds at
the sizes of ``ROWS``, filled beforehand by

    KKL_BENCH_CACHE=$KKL_BENCH_TRAINED_CACHE kkl-bench run --profile standard \\
        --track more-systems --regime sinusoid --system lorenz96-n10 \\
        --estimator autonomous_kkl injection_kkl --results <somewhere>

Without the variable it is
skipped: a missing trained model would be trained here, for hours. Run with
``python -m pytest tests/benchmarks/test_untrained_models.py --benchmark-only -s``; it
prints and records (``extra_info``) each row's cost untrained over trained.
"""

import math
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import pytest

from kkl_bench.analysis import scaling, scaling_timing
from kkl_bench.run.spec import RunSpec
from kkl_bench.suite.task import get_profile
from tests.benchmarks.test_estimate_cost import one_thread  # noqa: F401 (fixture)

ROWS = (("autonomous_kkl", 10), ("injection_kkl", 10))
CACHE = os.environ.get("KKL_BENCH_TRAINED_CACHE")


@pytest.mark.skipif(
    CACHE is None, reason="set KKL_BENCH_TRAINED_CACHE to a cache of trained models"
)
def test_untrained_models_cost_what_trained_ones_cost(benchmark):
    spec = RunSpec(
        tuple(name for name, _ in ROWS),
        tuple(scaling.system_name(n) for _, n in ROWS),
        (scaling.REGIME,),
        get_profile("standard"),
        tracks=(scaling.TRACK,),
        cache_dir=Path(CACHE),
    )
    with tempfile.TemporaryDirectory() as untrained:
        fitted = {}
        for name, n in ROWS:
            (trained,) = scaling_timing.fit_from_cache(spec, name, n, 0).values()
            fitted[name, n] = {
                "trained": {"torch": trained},
                "untrained": scaling_timing.fit_untrained(
                    replace(spec, cache_dir=Path(untrained)), name, n, 0, trained.fit_report()
                ),
            }
        models = {((name, kind), n): engines for (name, n), kinds in fitted.items()
                  for kind, engines in kinds.items()}  # fmt: skip
        timings = benchmark.pedantic(
            lambda: scaling_timing.time_estimators(spec, models), rounds=1, iterations=1
        )
    timings["row"] = timings["estimator"].str[0]  # (name, kind)
    timings["kind"] = timings["estimator"].str[1]
    for (name, batch), costs in timings.groupby(["row", "batch"]):
        by_kind = costs.set_index("kind")["us_per_step"]
        ratio = by_kind["untrained"] / by_kind["trained"]
        benchmark.extra_info[f"{name} batch {batch}: untrained / trained"] = ratio
        print(f"{name}, batch {batch}: trained {by_kind['trained']:.3g} µs, untrained "
              f"{by_kind['untrained']:.3g} µs a trajectory-step ({ratio:.3f})")  # fmt: skip
        assert math.isfinite(ratio)
