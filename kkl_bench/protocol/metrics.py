"""Per-trajectory error metrics on the steady-state window (protocol section 5).

All functions take ``x, x_hat: (batch, steps, n_x)`` and return one value per
trajectory. A trajectory is *diverged* when its estimate holds NaN or inf anywhere, or
when its NRMSE exceeds :data:`DIVERGENCE_NRMSE` (an error far beyond the states' own
spread: finite but meaningless); a diverged trajectory scores ``inf`` on every metric
(:func:`mark_diverged`), so it is counted and left out of every mean over the others.
"""

from __future__ import annotations

import math

import numpy as np

from kkl_bench.protocol import TRANSIENT_FRACTION


def steady_state_start(steps: int) -> int:
    """First scored sample: ``ceil(0.05 steps)`` (51 for 1001 samples)."""
    return math.ceil(TRANSIENT_FRACTION * steps)


def _steady(x: np.ndarray, x_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if x.shape != x_hat.shape or x.ndim != 3:
        raise ValueError(
            f"x and x_hat must both be (batch, steps, n_x); got {x.shape} and {x_hat.shape}"
        )
    start = steady_state_start(x.shape[1])
    return x[:, start:], x_hat[:, start:]


DIVERGENCE_NRMSE = 10.0
"""A trajectory whose NRMSE exceeds this has diverged (protocol section 5): its error is ten
times the spread of the test set's states, where an estimate frozen at the states' mean
scores about 1."""
DIVERGED_METRICS = ("rmse", "smape", "nrmse", "per_state_rmse", "settling_time_s")
"""The per-trajectory metrics of a cell that a diverged trajectory scores ``inf`` on."""


def beyond_bound(nrmse_values) -> np.ndarray:
    """``(batch,)`` True where a trajectory's NRMSE is not at most :data:`DIVERGENCE_NRMSE`
    (a non-finite one included)."""
    return ~(np.asarray(nrmse_values, dtype=float) <= DIVERGENCE_NRMSE)


def mark_diverged(metrics: dict) -> dict:
    """``metrics`` (per-trajectory lists, :data:`DIVERGED_METRICS`, as a cell stores them)
    with ``inf`` on every metric of each trajectory beyond the bound (:func:`beyond_bound`
    of its ``nrmse``): the one place the divergence rule is applied to scored cells, new
    and stored alike."""
    if not len(metrics.get("nrmse", [])):
        return metrics
    out = beyond_bound(metrics["nrmse"])
    if not out.any():
        return metrics
    marked = dict(metrics)
    for name in DIVERGED_METRICS:
        values = metrics.get(name)
        if values is None or not len(values):
            continue
        values = np.asarray(values, dtype=float)
        mask = out.reshape(-1, *([1] * (values.ndim - 1)))
        marked[name] = np.where(mask, np.inf, values).tolist()
    return marked


def diverged(x_hat: np.ndarray) -> np.ndarray:
    """``(batch,)`` True where the estimate holds NaN or inf anywhere."""
    return ~np.isfinite(x_hat).all(axis=(1, 2))


def _with_divergence(values: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """``values`` with ``inf`` for every trajectory of the *whole* ``x_hat`` that diverged."""
    return np.where(diverged(x_hat), np.inf, values)


def per_state_rmse(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """``(batch, n_x)`` RMSE of each state component over the steady state."""
    x_steady, x_hat_steady = _steady(x, x_hat)
    with np.errstate(invalid="ignore", over="ignore"):
        values = np.sqrt(np.mean((x_steady - x_hat_steady) ** 2, axis=1))
    return np.where(diverged(x_hat)[:, None], np.inf, values)


def rmse(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """``(batch,)`` RMSE over steady-state samples and all state components."""
    x_steady, x_hat_steady = _steady(x, x_hat)
    with np.errstate(invalid="ignore", over="ignore"):
        values = np.sqrt(np.mean((x_steady - x_hat_steady) ** 2, axis=(1, 2)))
    return _with_divergence(values, x_hat)


def smape(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """``(batch,)`` element-wise SMAPE in percent; a 0/0 term counts as 0."""
    x_steady, x_hat_steady = _steady(x, x_hat)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        denominator = (np.abs(x_steady) + np.abs(x_hat_steady)) / 2.0
        terms = np.where(denominator == 0.0, 0.0, np.abs(x_steady - x_hat_steady) / denominator)
        values = 100.0 * np.mean(terms, axis=(1, 2))
    return _with_divergence(values, x_hat)


def state_scale(x: np.ndarray) -> np.ndarray:
    """``(n_x,)`` standard deviation of each state over a whole test set's steady state."""
    start = steady_state_start(x.shape[1])
    return np.std(x[:, start:].reshape(-1, x.shape[-1]), axis=0)


def nrmse(x: np.ndarray, x_hat: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(batch,)`` mean over states of ``RMSE_i / scale_i`` (see :func:`state_scale`)."""
    return np.mean(per_state_rmse(x, x_hat) / scale, axis=1)


SETTLING_WINDOW_S = 1.0
"""Length of the sliding window of :func:`settling_time` (s)."""
SETTLING_THRESHOLD = 0.1
"""Normalized RMSE under which :func:`settling_time` counts the error as settled."""


def settling_time(
    x: np.ndarray,
    x_hat: np.ndarray,
    scale: np.ndarray,
    dt: float,
    window_s: float = SETTLING_WINDOW_S,
    threshold: float = SETTLING_THRESHOLD,
) -> np.ndarray:
    """``(batch,)`` seconds until the error settles, over the whole trajectory (no transient cut).

    The error of sample ``k`` is ``mean_i ((x_i - x_hat_i) / scale_i)^2``; its
    root mean over a window of ``window_s`` seconds is the window's normalized
    RMSE. The settling time is the start of the first window from which on
    every window's normalized RMSE is below ``threshold``: 0 if the estimate
    is within it from the first window, ``inf`` if the last window is not
    (never settled) or the estimate diverged.
    """
    if x.shape != x_hat.shape or x.ndim != 3:
        raise ValueError(
            f"x and x_hat must both be (batch, steps, n_x); got {x.shape} and {x_hat.shape}"
        )
    window = max(1, round(window_s / dt))
    if x.shape[1] < window:
        raise ValueError(f"trajectories of {x.shape[1]} samples are shorter than one window")
    with np.errstate(invalid="ignore", over="ignore"):
        error = np.mean(((x - x_hat) / scale) ** 2, axis=2)
        total = np.cumsum(np.pad(error, ((0, 0), (1, 0))), axis=1)
        sliding = np.sqrt((total[:, window:] - total[:, :-window]) / window)
    above = ~(sliding < threshold)  # NaN counts as above
    n_windows = above.shape[1]
    last_above = np.where(above.any(axis=1), n_windows - 1 - np.argmax(above[:, ::-1], axis=1), -1)
    start = last_above + 1
    times = np.where(start < n_windows, start * dt, np.inf)
    return _with_divergence(times, x_hat)
