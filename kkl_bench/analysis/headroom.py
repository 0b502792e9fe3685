"""Headroom of a task: how far the UKF is from the particle filter's limit, on validation data.

A task has headroom when the Gaussian filters given the exact model are not
already optimal, so that a better estimator can show it. Track authors choose
a task's settings with :func:`headroom` (``kkl-bench headroom``), which never
touches a test stream: it draws trajectories of the task's regime, box and
measurement model from a validation stream of the training generator, runs the
UKF and the particle filter fitted for the task's truth on them, and reports
their RMSE over the scored window and the ratio (protocol 7.6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kkl_bench import variants
from kkl_bench.estimator import FitContext
from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.run.spec import conditioned_context, task_conditions
from kkl_bench.suite.task import Task

STREAM = "headroom/validation"
"""The training generator's stream the validation trajectories come from."""


@dataclass(frozen=True)
class Headroom:
    """The UKF's and the limit's RMSE (means over trajectories) on a task's validation data."""

    task: Task
    n_trajectories: int
    ukf_rmse: float
    limit_rmse: float
    limit: str

    @property
    def ratio(self) -> float:
        return self.ukf_rmse / self.limit_rmse


def _rmse(estimator, context: FitContext, data) -> float:
    x_hat = estimator.fit(context).estimate(data.t, data.y, data.u)
    start = steady_state_start(data.x.shape[1])
    per_trajectory = np.sqrt(np.mean((x_hat[:, start:] - data.x[:, start:]) ** 2, axis=(1, 2)))
    return float(np.mean(per_trajectory))


def headroom(
    task: Task, n: int = 4, limit: str = "particle_filter[n=2000]", seed: int = 0
) -> Headroom:
    """UKF against ``limit`` on ``n`` validation trajectories of ``task`` (its regime, box,
    horizon and measurement model, the protocol's process noise), both told the task's
    truth. A diverged trajectory makes its filter's RMSE infinite."""
    definition = task.definition
    context = conditioned_context(task.system, seed, task_conditions(task, with_box=True))
    data = context.training.simulate(
        definition.regime(),
        n,
        stream=f"{STREAM}/{task.track}/{task.regime}",
        n_samples=definition.n_samples,
        x0_low=context.x0_low,
        x0_high=context.x0_high,
    )
    with np.errstate(invalid="ignore", over="ignore"):
        ukf = _rmse(variants.build("ukf"), context, data)
        best = _rmse(variants.build(limit), context, data)
    return Headroom(
        task,
        n,
        ukf if np.isfinite(ukf) else np.inf,
        best if np.isfinite(best) else np.inf,
        limit,
    )
