"""Extended Kalman filter baseline (filterpy), on the exact discrete-time model."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from kkl_bench.estimators.kalman import KalmanBaseline, box_prior, measurement_covariance

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
    """

    name = "ekf"

    def __init__(self, inflation: float = 1.0) -> None:
        self.inflation = inflation
        if not (isinstance(inflation, int | float) and inflation >= 1.0):
            raise ValueError(f"ekf: inflation={inflation!r} must be a number of at least 1")

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
