"""Choosing a model-based row's free settings on validation streams (never a test stream).

A filter's free settings (an inflation, a robust threshold) are chosen per fit, like a
learned row's weights: each candidate runs on the same validation trajectories of the
training generator, and the one with the lowest RMSE over the scored window wins (the
first of equals, so a grid listed from the plainest setting keeps it on ties).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.training import FORCED_TRAINING, TrainingData

VALIDATION_TRAJECTORIES = 16
"""Forced validation trajectories every model-based row tunes on."""


def validation_data(
    training: TrainingData, stream: str, count: int = VALIDATION_TRAJECTORIES
) -> Trajectories:
    """``count`` forced trajectories of ``training``'s stream ``stream`` (simulated with the
    task's measurement model)."""
    return training.simulate(FORCED_TRAINING, count, stream=stream)


def validation_error(x_hat: np.ndarray, x: np.ndarray) -> float:
    """RMSE of ``x_hat`` against ``x`` (both ``(batch, steps, n_x)``) over the scored window;
    infinite if it is not finite (a candidate that loses a trajectory never wins)."""
    start = steady_state_start(x.shape[1])
    with np.errstate(over="ignore", invalid="ignore"):  # a diverged candidate: inf or nan
        error = float(np.sqrt(np.mean((x_hat[:, start:] - x[:, start:]) ** 2)))
    return error if np.isfinite(error) else float("inf")


def label(setting: dict[str, Any]) -> str:
    """``{"threshold": 1.345, "inflation": 1.0}`` -> ``"threshold=1.345,inflation=1"``
    (text values as they are)."""
    return ",".join(
        f"{key}={value}" if isinstance(value, str) else f"{key}={value:g}"
        for key, value in setting.items()
    )


def choose(
    candidates: Sequence[dict[str, Any]],
    estimate: Callable[[dict[str, Any], Trajectories], np.ndarray],
    data: Trajectories,
) -> tuple[dict[str, Any], dict[str, float]]:
    """The candidate whose ``estimate(candidate, data)`` has the lowest
    :func:`validation_error`, and every candidate's error by :func:`label`."""
    scores = {label(c): validation_error(estimate(c, data), data.x) for c in candidates}
    best = min(candidates, key=lambda c: scores[label(c)])
    return best, scores
