"""Per-trajectory error metrics on the steady-state window (protocol section 5).

All functions take ``x, x_hat: (batch, steps, n_x)`` and return one value per
trajectory; a trajectory whose estimate holds NaN or inf anywhere is
*diverged* and scores ``inf``.
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
