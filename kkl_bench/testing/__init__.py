"""The conformance kits a plugin author runs: :mod:`.estimators` for an estimator (after
scikit-learn's ``check_estimator``), :mod:`.systems` for a system; ``kkl-bench check NAME``
runs either.

Layer: the top of the plugin face; it fits estimators as a run does, so it may import the
run layer and everything under it."""

from kkl_bench.testing.estimators import (
    CHECK_SYSTEMS,
    Conformance,
    check_budget,
    check_estimator,
    check_systems,
    estimator_checks,
    run_checks,
)
from kkl_bench.testing.kit import describe
from kkl_bench.testing.systems import SystemConformance, check_system, run_system_checks

__all__ = [
    "CHECK_SYSTEMS",
    "Conformance",
    "SystemConformance",
    "check_budget",
    "check_estimator",
    "check_system",
    "check_systems",
    "describe",
    "estimator_checks",
    "run_checks",
    "run_system_checks",
]
