"""What the EKF and UKF baselines share: the protocol's prior and the filtering loop.

Both filters run the protocol's discrete-time model: the RK4 step with the
known held input as transition, ``Q = sigma_w^2 I`` (the process noise is
added after each step), ``R = sigma_v^2 I``, and an initial estimate at the
centre of the x0 box with the covariance of the uniform box distribution,
``diag((high - low)^2 / 12)``. On a task with another measurement model
(:mod:`kkl_bench.measurement`) they read the state through its sensor (in
``system.h`` and its Jacobian), take ``R`` as the noise law's variance (plus a
quantizer's ``step^2 / 12``) and update only where ``y`` is present.

Two engines run the same filter (``engine=`` of both estimators): ``"reference"`` (the
default, what the published accuracy cells come from), filterpy's filter advanced one
trajectory and one sample at a time in Python, and ``"compiled"``, the same arithmetic
in numba kernels (:mod:`kkl_bench.estimators.kalman_kernels`) over the system's compiled
model: what ``kkl-bench cost`` times as the row's online cost, with the reference beside
it (protocol 6.3). A system without a compiled model
(:meth:`~kkl_bench.protocol.system.System.compiled` is None: a plugin's) runs the
reference engine; the fit report names the engine that runs.
"""

from __future__ import annotations

import math
from abc import abstractmethod

import numpy as np

from kkl_bench.calibration import CalibratesOnLoggedData
from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.protocol.compiled import CompiledModel

ENGINES = ("compiled", "reference")
"""The engines a model-based filter runs on (the module docstring)."""


def check_engine(owner: str, engine: object) -> None:
    """Raise ``ValueError`` naming ``engine`` and the valid ones unless it is one."""
    if engine not in ENGINES:
        raise ValueError(f"{owner}: unknown engine={engine!r}; valid engines: {', '.join(ENGINES)}")


def measurement_covariance(context: FitContext) -> np.ndarray:
    """``R = variance I``, ``(n_y, n_y)``: the task's noise law's variance, plus the sensor's
    loss (``kkl_bench.measurement.MeasurementModel.variance``)."""
    return context.measurement.variance * np.eye(context.system.n_y)


def box_prior(context: FitContext) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(n_x,)`` and covariance ``(n_x, n_x)`` of the uniform x0 box."""
    low, high = context.x0_low, context.x0_high
    return (low + high) / 2.0, np.diag((high - low) ** 2 / 12.0)


class KalmanBaseline(CalibratesOnLoggedData, Estimator):
    """A Kalman filter on one of two engines (the module docstring).

    Subclasses build the reference engine's filterpy filter (:meth:`make_filter`), take
    one of its predict-update steps (:meth:`step`), and run the compiled kernel
    (:meth:`run_compiled`); ``self.engine`` is the engine asked for. A filter that hits
    a singular matrix yields NaN from there on, so the trajectory is reported as
    diverged. Nothing is trained, so the seed changes nothing: it is run once. Given
    logged data (``mismatch``), the filter runs on the model calibrated on them
    (:mod:`kkl_bench.calibration`).
    """

    uses_seed = False
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    engine: str

    def fit(self, context: FitContext):
        super().fit(context)
        fitted = self.check_fitted()
        self.model_ = fitted.system.compiled() if self.engine == "compiled" else None
        return self

    @property
    def engine_used(self) -> str:
        """The engine :meth:`estimate` runs: the one asked for, or ``"reference"`` where
        the system has no compiled model."""
        return "reference" if getattr(self, "model_", None) is None else "compiled"

    def fit_report(self) -> dict:
        return {**super().fit_report(), "engine": self.engine_used}

    def flops_per_step(self) -> float:
        """Floating-point operations of one trajectory-step (a predict and an update) on the
        fitted system, counted from the algorithm with dense matrices (NaN for a system
        without a compiled model, whose drift has no declared count)."""
        model = self.check_fitted().system.compiled()
        return math.nan if model is None else float(self.count_flops(model))

    @abstractmethod
    def count_flops(self, model: CompiledModel) -> int:
        """Flops of one predict and one update on ``model``."""

    @abstractmethod
    def run_compiled(self, model: CompiledModel, context: FitContext, dt: float, y, u, out) -> None:
        """Fill ``out: (batch, steps, n_x)`` (NaN on entry) from ``y: (batch, steps, n_y)``
        and ``u: (batch, steps)`` with the compiled kernel on ``model``."""

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
        if self.model_ is not None:
            y = np.ascontiguousarray(y, dtype=np.float64)
            u = np.ascontiguousarray(u[..., 0], dtype=np.float64)
            self.run_compiled(self.model_, context, dt, y, u, x_hat)
            return x_hat
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
