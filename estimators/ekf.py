"""Extended Kalman filter baseline (filterpy and its compiled twin), on the exact discrete-time
model."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from kkl_bench.estimators import kalman_kernels
from kkl_bench.estimators.kalman import (
    KalmanBaseline,
    box_prior,
    check_engine,
    measurement_covariance,
)

from kkl_bench.estimator import FitContext
from kkl_bench.protocol.simulate import rk4_step, rk4_step_jacobian
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators


class _RK4ExtendedKalmanFilter(ExtendedKalmanFilter):
    """filterpy's EKF with the RK4 step as the (nonlinear) transition.

    filterpy's ``predict_x`` is linear (``F x + B u``): here it is the RK4
    step, and ``F`` is its exact Jacobian at the prior mean.
    """

    def __init__(self, system: System, dt: float, inflation: float = 1.0) -> None:
        super().__init__(dim_x=system.n_x, dim_z=system.n_y)
        self.system = system
        self.dt = dt
        self.inflation = inflation

    def predict(self, u=0.0):
        self.F = rk4_step_jacobian(self.system, self.x[:, 0], np.asarray(u), self.dt)
        super().predict(u)
        if self.inflation != 1.0:  # P = inflation F P F^T + Q
            self.P = self.inflation * (self.P - self.Q) + self.Q
            self.P_prior = self.P.copy()

    def predict_x(self, u=0.0):
        self.x = rk4_step(self.system, self.x[:, 0], np.asarray(u), self.dt)[:, None]


@estimators.register("ekf")
class ExtendedKalman(KalmanBaseline):
    """EKF with the RK4 transition, its exact Jacobian and the protocol's Q, R and prior.

    Parameters
    ----------
    inflation: factor on the propagated covariance, ``P = inflation F P F^T + Q`` (1: the
        plain EKF; DAPPER's ``ExtKF(infl=a)`` at step ``dt`` is ``inflation = a**dt``).
    engine: ``"compiled"`` or ``"reference"`` (filterpy; :mod:`kkl_bench.estimators.kalman`).
    """

    name = "ekf"

    def __init__(self, inflation: float = 1.0, engine: str = "reference") -> None:
        self.inflation = inflation
        self.engine = engine
        if not (isinstance(inflation, int | float) and inflation >= 1.0):
            raise ValueError(f"ekf: inflation={inflation!r} must be a number of at least 1")
        check_engine("ekf", engine)

    def count_flops(self, model):
        n, m = model.n_x, model.n_y
        predict = model.step_flops + model.step_jacobian_flops + 4 * n**3 + n**2  # F P F^T + Q
        gain = m * n + 2 * n * n * m + 2 * m * m * n + m * m + 2 * m**3 + 2 * n * m * m
        correction = m + 2 * n * m  # the residual and x + K r
        joseph = 2 * n * n * m + n * n + 4 * n**3 + 2 * n * m * m + 2 * n * n * m + n * n
        return predict + gain + correction + joseph

    def run_compiled(self, model, context, dt, y, u, out):
        mean, covariance = box_prior(context)
        kalman_kernels.ekf(
            *model.functions, model.p, model.q, model.s, model.g, y, u, dt, mean, covariance,
            context.sigma_w**2 * np.eye(model.n_x), measurement_covariance(context),
            float(self.inflation), out,
        )  # fmt: skip

    def make_filter(self, context: FitContext, dt: float):
        kalman_filter = _RK4ExtendedKalmanFilter(context.system, dt, self.inflation)
        mean, covariance = box_prior(context)
        kalman_filter.x = mean[:, None].copy()
        kalman_filter.P = covariance
        kalman_filter.Q = context.sigma_w**2 * np.eye(context.system.n_x)
        kalman_filter.R = measurement_covariance(context)
        return kalman_filter

    def step(self, kalman_filter, u_previous, y):
        system = kalman_filter.system
        if u_previous is not None:
            kalman_filter.predict(u_previous)
        if not np.isfinite(y).all():
            return kalman_filter.x[:, 0]
        kalman_filter.update(
            y[:, None],
            HJacobian=lambda x: system.h_jacobian(x[:, 0]),
            Hx=lambda x: system.h(x[:, 0])[:, None],
        )
        return kalman_filter.x[:, 0]
