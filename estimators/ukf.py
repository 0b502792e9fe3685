"""Unscented Kalman filter baseline (filterpy and its compiled twin), on the exact discrete-time
model."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from kkl_bench.estimators import kalman_kernels
from kkl_bench.estimators.kalman import (
    KalmanBaseline,
    box_prior,
    check_engine,
    measurement_covariance,
)

from kkl_bench.estimator import FitContext
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.registry import estimators


class _BatchedSigmaUKF(UnscentedKalmanFilter):
    """filterpy's UKF, propagating all sigma points through RK4 in one call."""

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        self.sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = self.fx(self.sigmas, dt, **fx_args)


@estimators.register("ukf")
class UnscentedKalman(KalmanBaseline):
    """UKF with Merwe scaled sigma points, the RK4 transition and the protocol's Q, R and prior.

    Parameters
    ----------
    alpha, beta, kappa: Merwe sigma-point parameters (spread, prior knowledge, secondary scaling).
    engine: ``"compiled"`` or ``"reference"`` (filterpy; :mod:`kkl_bench.estimators.kalman`).
    """

    name = "ukf"

    def __init__(
        self, alpha: float = 0.5, beta: float = 2.0, kappa: float = 0.0, engine: str = "reference"
    ) -> None:
        self.alpha = alpha
        self.beta = beta
        self.kappa = kappa
        self.engine = engine
        check_engine("ukf", engine)

    def count_flops(self, model):
        n, m = model.n_x, model.n_y
        points = 2 * n + 1
        sigma_points = n * n + n**3 // 3 + n * n + 2 * n * n  # scale, Cholesky, x -/+ U[k]

        def transform(size):  # the unscented transform of `points` vectors of `size`
            return 2 * points * size + points * size + 3 * points * size * size + size * size

        predict = 2 * sigma_points + points * model.step_flops + transform(n)
        update = transform(m) + 2 * m**3 + points * (n + m + 3 * n * m)  # S^-1, Pxz
        update += 2 * n * m * m + 3 * n * m + 2 * n * m * m + 2 * n * n * m + n * n
        return predict + update

    def run_compiled(self, model, context, dt, y, u, out):
        points = MerweScaledSigmaPoints(
            model.n_x, alpha=self.alpha, beta=self.beta, kappa=self.kappa
        )  # filterpy's weights, and its spread n + lambda computed as filterpy does
        lambda_ = points.alpha**2 * (model.n_x + points.kappa) - model.n_x
        spread = lambda_ + model.n_x
        mean, covariance = box_prior(context)
        kalman_kernels.ukf(
            *model.functions, model.p, model.q, model.s, model.g, y, u, dt, mean, covariance,
            context.sigma_w**2 * np.eye(model.n_x), measurement_covariance(context),
            points.Wm, points.Wc, spread, out,
        )  # fmt: skip

    def make_filter(self, context: FitContext, dt: float):
        system = context.system
        points = MerweScaledSigmaPoints(
            system.n_x, alpha=self.alpha, beta=self.beta, kappa=self.kappa
        )
        kalman_filter = _BatchedSigmaUKF(
            dim_x=system.n_x,
            dim_z=system.n_y,
            dt=dt,
            hx=system.h,
            fx=lambda x, dt, u=0.0: rk4_step(system, x, np.full(x.shape[:-1], u), dt),
            points=points,
        )
        mean, covariance = box_prior(context)
        kalman_filter.x = mean.copy()
        kalman_filter.P = covariance
        kalman_filter.Q = context.sigma_w**2 * np.eye(system.n_x)
        kalman_filter.R = measurement_covariance(context)
        # the first update comes before any predict: its sigma points are the prior's
        kalman_filter.sigmas_f = points.sigma_points(kalman_filter.x, kalman_filter.P)
        return kalman_filter

    def step(self, kalman_filter, u_previous, y):
        if u_previous is not None:
            kalman_filter.predict(u=u_previous)
        if np.isfinite(y).all():
            kalman_filter.update(y)
        return kalman_filter.x.copy()
