"""Scoring one fitted estimator on one test set: the protocol's metrics and the timed estimate."""

from __future__ import annotations

import time

import numpy as np

from kkl_bench.estimator import Estimator
from kkl_bench.protocol.metrics import (
    mark_diverged,
    nrmse,
    per_state_rmse,
    rmse,
    settling_time,
    smape,
)
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.run.results import KeptEstimate
from kkl_bench.suite.task import TestSet
from kkl_bench.support import convergence

WARM_UP_STEPS = 20
"""Samples of one trajectory an estimator runs on, untimed, before it is timed."""


def warm_up(estimator: Estimator, data: Trajectories) -> None:
    """Run ``estimator`` untimed on the first :data:`WARM_UP_STEPS` samples of the first
    trajectory of ``data`` (first-call costs: lazy imports, allocator growth)."""
    estimator.estimate(
        data.t[:WARM_UP_STEPS], data.y[:1, :WARM_UP_STEPS].copy(), data.u[:1, :WARM_UP_STEPS].copy()
    )


def timed_estimate(estimator: Estimator, data: Trajectories) -> tuple[np.ndarray, float]:
    """``estimator``'s estimate ``(batch, steps, n_x)`` on copies of ``data`` and its wall
    time (s)."""
    start = time.perf_counter()
    x_hat = np.asarray(estimator.estimate(data.t.copy(), data.y.copy(), data.u.copy()), dtype=float)
    return x_hat, time.perf_counter() - start


def training_diverged(estimator: Estimator) -> bool:
    """Whether the fit report of ``estimator`` says one of its trainings diverged
    (protocol 6.5): an estimate that is never finite is then that training's outcome,
    scored as diverged on every trajectory, not an estimator fault."""
    return convergence.verdict([estimator.fit_report()]) == convergence.DIVERGED


def score(estimator: Estimator, test_set: TestSet) -> tuple[dict, KeptEstimate]:
    """Run ``estimator`` on ``test_set`` and compute the protocol's metrics.

    Returns the metric and timing fields of a :class:`CellResult` and the
    truth and estimate of the first test trajectory. Raises ``ValueError`` if
    the estimate has the wrong shape, or is NaN or inf from the first sample on every
    trajectory while no training of the estimator diverged (:func:`training_diverged`).
    """
    data = test_set.data
    dt = float(data.t[1] - data.t[0])
    warm_up(estimator, data)
    x_hat, elapsed = timed_estimate(estimator, data)
    if x_hat.shape != data.x.shape:
        raise ValueError(
            f"estimate returned shape {x_hat.shape}; expected {data.x.shape} (batch, steps, n_x)"
        )
    if not np.isfinite(x_hat[:, 0]).all(axis=-1).any() and not training_diverged(estimator):
        raise ValueError(
            "estimate is NaN or inf from the first sample on every trajectory: an estimator "
            "fault, not a divergence (a diverged trajectory loses track after a start)"
        )
    metrics = {
        "rmse": rmse(data.x, x_hat).tolist(),
        "smape": smape(data.x, x_hat).tolist(),
        "nrmse": nrmse(data.x, x_hat, test_set.state_scale).tolist(),
        "per_state_rmse": per_state_rmse(data.x, x_hat).tolist(),
        "settling_time_s": settling_time(data.x, x_hat, test_set.state_scale, dt).tolist(),
        "estimate_us_per_step": 1e6 * elapsed / (x_hat.shape[0] * x_hat.shape[1]),
    }
    return mark_diverged(metrics), KeptEstimate(t=data.t, x=data.x[0], x_hat=x_hat[0])
