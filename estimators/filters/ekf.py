"""Extended Kalman filter baseline (filterpy and its compiled twin), on the exact discrete-time
model."""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from kkl_bench.estimators.filters import kalman_kernels, kalman_large, kalman_unrolled
from kkl_bench.estimators.filters.kalman import KalmanBaseline, huber_noise

from kkl_bench.protocol.simulate import rk4_step, rk4_step_jacobian
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators
from kkl_bench.support.kernel_cache import bind


class _RK4ExtendedKalmanFilter(ExtendedKalmanFilter):
    """filterpy's EKF with the RK4 step, then the system's constraint, as the (nonlinear)
    transition.

    filterpy's ``predict_x`` is linear (``F x + B u``): here it is the RK4
    step, and ``F`` is its exact Jacobian at the prior mean (the constraint, a
    reflection where it acts, projects the mean and leaves ``F`` as it is).
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
        step = rk4_step(self.system, self.x[:, 0], np.asarray(u), self.dt)
        self.x = self.system.constrain(step)[:, None]


@estimators.register("ekf")
class ExtendedKalman(KalmanBaseline):
    """EKF with the RK4 transition, its exact Jacobian and the protocol's Q, R and prior,
    built for the task's sensor (:mod:`kkl_bench.estimators.filters.kalman`).

    Parameters
    ----------
    inflation: factor on the propagated covariance, ``P = inflation F P F^T + Q`` (1: the
        plain EKF; DAPPER's ``ExtKF(infl=a)`` at step ``dt`` is ``inflation = a**dt``), or
        None (default): 1 on the protocol's measurement model, chosen on validation
        trajectories on any other.
    robust: ``"auto"`` (default: Huber's update under a heavy-tailed noise law),
        ``"huber"`` or ``"none"``.
    threshold: Huber's ``c`` in predicted standard deviations, or None (default): chosen on
        validation trajectories.
    quantizer: ``"auto"`` (default: chosen on validation trajectories), ``"noise"`` (a
        quantizer read as additive noise) or ``"in-model"``.
    engine: ``"compiled"`` or ``"reference"`` (filterpy).
    """

    name = "ekf"

    def __init__(
        self,
        inflation: float | None = None,
        robust: str = "auto",
        threshold: float | None = None,
        quantizer: str = "auto",
        engine: str = "reference",
    ) -> None:
        self.store_design(
            inflation=inflation,
            robust=robust,
            threshold=threshold,
            quantizer=quantizer,
            engine=engine,
        )

    def count_flops(self, model):
        robust = math.isfinite(self.settings_["threshold"])
        if kalman_large.takes(model):
            nonzeros = kalman_large.structural_nonzeros(model)
            return kalman_large.flops_per_step(model, nonzeros, robust)
        n, m = model.n_x, model.n_y
        predict = model.step_flops + model.step_jacobian_flops + 4 * n**3 + n**2  # F P F^T + Q
        gain = m * n + 2 * n * n * m + 2 * m * m * n + m * m + 2 * m**3 + 2 * n * m * m
        correction = m + 2 * n * m  # the residual and x + K r
        joseph = 2 * n * n * m + n * n + 4 * n**3 + 2 * n * m * m + 2 * n * n * m + n * n
        huber = 5 * m + m * m if robust else 0
        return predict + gain + correction + joseph + huber

    def run_compiled(self, model, settings, dt, y, u, out):
        mean, covariance, Q = self.prior()
        if kalman_unrolled.unrollable(model):
            kalman_unrolled.run_ekf(
                model, y, u, dt, mean, covariance, Q, self.R_, settings["inflation"],
                settings["threshold"], out,
            )  # fmt: skip
            return
        kernel = kalman_large.ekf if kalman_large.takes(model) else kalman_kernels.ekf
        bind(kernel, *model.functions)(
            model.p, model.q, model.s, model.g, y, u, dt, mean, covariance,
            Q, self.R_, settings["inflation"], settings["threshold"], out,
        )  # fmt: skip

    def make_filter(self, settings, dt):
        system = self.filter_system(settings)
        kalman_filter = _RK4ExtendedKalmanFilter(system, dt, settings["inflation"])
        kalman_filter.x, kalman_filter.P, kalman_filter.Q = self.prior()
        kalman_filter.x = kalman_filter.x[:, None].copy()
        kalman_filter.R = self.R_
        kalman_filter.threshold = settings["threshold"]
        return kalman_filter

    def step(self, kalman_filter, u_previous, y):
        system = kalman_filter.system
        if u_previous is not None:
            kalman_filter.predict(u_previous)
        if not np.isfinite(y).all():
            return kalman_filter.x[:, 0]
        x = kalman_filter.x[:, 0]
        if math.isfinite(kalman_filter.threshold):
            H = system.h_jacobian(x)
            S = H @ kalman_filter.P @ H.T + self.R_
            kalman_filter.R = huber_noise(self.R_, y - system.h(x), S, kalman_filter.threshold)
        kalman_filter.update(
            y[:, None],
            HJacobian=lambda x: system.h_jacobian(x[:, 0]),
            Hx=lambda x: system.h(x[:, 0])[:, None],
        )
        return kalman_filter.x[:, 0]
