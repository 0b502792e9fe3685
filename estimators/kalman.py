"""What the EKF and UKF baselines share: the protocol's prior and the filtering loop.

Both filters run the protocol's discrete-time model: the RK4 step with the
known held input as transition, ``Q = sigma_w^2 I`` (the process noise is
added after each step), ``R = sigma_v^2 I``, and an initial estimate at the
centre of the x0 box with the covariance of the uniform box distribution,
``diag((high - low)^2 / 12)``. On a task with another measurement model
(:mod:`kkl_bench.measurement`) they read the state through its sensor (in
``system.h`` and its Jacobian), take ``R`` as the noise law's variance (plus a
quantizer's ``step^2 / 12``) and update only where ``y`` is present.
"""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from kkl_bench.calibration import CalibratesOnLoggedData
from kkl_bench.estimator import Estimator, FitContext


def measurement_covariance(context: FitContext) -> np.ndarray:
    """``R = variance I``, ``(n_y, n_y)``: the task's noise law's variance, plus the sensor's
    loss (``kkl_bench.measurement.MeasurementModel.variance``)."""
    return context.measurement.variance * np.eye(context.system.n_y)


def box_prior(context: FitContext) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(n_x,)`` and covariance ``(n_x, n_x)`` of the uniform x0 box."""
    low, high = context.x0_low, context.x0_high
    return (low + high) / 2.0, np.diag((high - low) ** 2 / 12.0)


class KalmanBaseline(CalibratesOnLoggedData, Estimator):
    """A filterpy filter run trajectory by trajectory over the batch.

    Subclasses build the filter (:meth:`make_filter`) and take one
    predict-update step (:meth:`step`). A filter that hits a singular matrix
    yields NaN from there on, so the trajectory is reported as diverged.
    Nothing is trained, so the seed changes nothing: it is run once. Given
    logged data (``mismatch``), the filter runs on the model calibrated on them
    (:mod:`kkl_bench.calibration`).
    """

    uses_seed = False
    supported_measurements = frozenset({"sensor", "sampling", "noise"})

    @abstractmethod
    def make_filter(self, context: FitContext, dt: float):
        """A fresh filterpy filter at the box prior."""

    @abstractmethod
    def step(self, kalman_filter, u_previous: float | None, y: np.ndarray) -> np.ndarray:
        """Predict with ``u_previous`` (None at k = 0), update with ``y: (n_y,)`` if it is
        present (not NaN); return the posterior mean ``(n_x,)``."""

    def estimate(self, t, y, u):
        context = self.check_fitted()
        dt = float(t[1] - t[0]) if len(t) > 1 else context.dt
        batch, steps, _ = y.shape
        x_hat = np.full((batch, steps, context.system.n_x), np.nan)
        for b in range(batch):
            kalman_filter = self.make_filter(context, dt)
            for k in range(steps):
                u_previous = None if k == 0 else float(u[b, k - 1, 0])
                try:
                    with np.errstate(over="ignore", invalid="ignore"):
                        x_hat[b, k] = self.step(kalman_filter, u_previous, y[b, k])
                except (np.linalg.LinAlgError, ValueError):  # singular or non-finite matrices
                    x_hat[b, k] = np.nan
                    break
                if not np.all(np.isfinite(x_hat[b, k])):
                    break
        return x_hat
