"""Unscented Kalman filter baseline (filterpy and its compiled twin), on the exact discrete-time
model."""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter, unscented_transform
from kkl_bench.estimators.filters import kalman_kernels, kalman_large, kalman_unrolled
from kkl_bench.estimators.filters.kalman import KalmanBaseline, huber_noise

from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.registry import estimators
from kkl_bench.support.kernel_cache import bind


class _BatchedSigmaUKF(UnscentedKalmanFilter):
    """filterpy's UKF, propagating all sigma points through RK4 and the system's constraint
    in one call, with the propagated covariance inflated (``P = inflation (P - Q) + Q``,
    the sigma points then redrawn from it, as filterpy's ``predict`` draws them)."""

    inflation = 1.0

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        self.sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = self.fx(self.sigmas, dt, **fx_args)

    def predict(self, dt=None, UT=None, fx=None, **fx_args):
        super().predict(dt, UT, fx, **fx_args)
        if self.inflation != 1.0:
            self.P = self.inflation * (self.P - self.Q) + self.Q
            self.sigmas_f = self.points_fn.sigma_points(self.x, self.P)
            self.P_prior = np.copy(self.P)


@estimators.register("ukf")
class UnscentedKalman(KalmanBaseline):
    """UKF with Merwe scaled sigma points, the RK4 transition and the protocol's Q, R and
    prior, built for the task's sensor (:mod:`kkl_bench.estimators.filters.kalman`).

    Parameters
    ----------
    alpha, beta, kappa: Merwe sigma-point parameters (spread, prior knowledge, secondary scaling).
    inflation: factor on the propagated covariance, ``P = inflation (P - Q) + Q``, or None
        (default): 1 on the protocol's measurement model, chosen on validation trajectories
        on any other.
    robust: ``"auto"`` (default: Huber's update under a heavy-tailed noise law),
        ``"huber"`` or ``"none"``.
    threshold: Huber's ``c`` in predicted standard deviations, or None (default): chosen on
        validation trajectories.
    quantizer: ``"auto"`` (default: chosen on validation trajectories), ``"noise"`` (a
        quantizer read as additive noise, outside the sigma points) or ``"in-model"``
        (inside them).
    engine: ``"compiled"`` or ``"reference"`` (filterpy).
    """

    name = "ukf"

    def __init__(
        self,
        alpha: float = 0.5,
        beta: float = 2.0,
        kappa: float = 0.0,
        inflation: float | None = None,
        robust: str = "auto",
        threshold: float | None = None,
        quantizer: str = "auto",
        engine: str = "reference",
    ) -> None:
        self.alpha = alpha
        self.beta = beta
        self.kappa = kappa
        self.store_design(
            inflation=inflation,
            robust=robust,
            threshold=threshold,
            quantizer=quantizer,
            engine=engine,
        )

    def points(self, n_x: int) -> MerweScaledSigmaPoints:
        return MerweScaledSigmaPoints(n_x, alpha=self.alpha, beta=self.beta, kappa=self.kappa)

    def count_flops(self, model):
        n, m = model.n_x, model.n_y
        points = 2 * n + 1
        sigma_points = n * n + n**3 // 3 + n * n + 2 * n * n  # scale, Cholesky, x -/+ U[k]

        def transform(size):  # the unscented transform of `points` vectors of `size`
            return 2 * points * size + points * size + 3 * points * size * size + size * size

        predict = 2 * sigma_points + points * model.step_flops + transform(n)
        update = transform(m) + 2 * m**3 + points * (n + m + 3 * n * m)  # S^-1, Pxz
        update += 2 * n * m * m + 3 * n * m + 2 * n * m * m + 2 * n * n * m + n * n
        if math.isfinite(self.settings_["threshold"]):  # the weights and S once more
            update += 5 * m + m * m + transform(m)
        return predict + update

    def run_compiled(self, model, settings, dt, y, u, out):
        points = self.points(model.n_x)  # filterpy's weights, and its spread n + lambda
        lambda_ = points.alpha**2 * (model.n_x + points.kappa) - model.n_x
        mean, covariance, Q = self.prior()
        if kalman_unrolled.unrollable(model):
            kalman_unrolled.run_ukf(
                model, y, u, dt, mean, covariance, Q, self.R_, points.Wm, points.Wc,
                lambda_ + model.n_x, settings["inflation"], settings["threshold"], out,
            )  # fmt: skip
            return
        kernel = kalman_large.ukf if kalman_large.takes(model) else kalman_kernels.ukf
        bind(kernel, *model.functions)(
            model.p, model.q, model.s, model.g, y, u, dt, mean, covariance,
            Q, self.R_, points.Wm, points.Wc, lambda_ + model.n_x, settings["inflation"],
            settings["threshold"], out,
        )  # fmt: skip

    def make_filter(self, settings, dt):
        system = self.filter_system(settings)
        points = self.points(system.n_x)
        kalman_filter = _BatchedSigmaUKF(
            dim_x=system.n_x,
            dim_z=system.n_y,
            dt=dt,
            hx=system.h,
            fx=lambda x, dt, u=0.0: system.constrain(
                rk4_step(system, x, np.full(x.shape[:-1], u), dt)
            ),
            points=points,
        )
        kalman_filter.x, kalman_filter.P, kalman_filter.Q = self.prior()
        kalman_filter.R = self.R_
        kalman_filter.inflation = settings["inflation"]
        kalman_filter.threshold = settings["threshold"]
        # the first update comes before any predict: its sigma points are the prior's
        kalman_filter.sigmas_f = points.sigma_points(kalman_filter.x, kalman_filter.P)
        return kalman_filter

    def step(self, kalman_filter, u_previous, y):
        if u_previous is not None:
            kalman_filter.predict(u=u_previous)
        if np.isfinite(y).all():
            R = self.R_
            if math.isfinite(kalman_filter.threshold):
                outputs = np.atleast_2d([kalman_filter.hx(s) for s in kalman_filter.sigmas_f])
                predicted, S = unscented_transform(
                    outputs, kalman_filter.Wm, kalman_filter.Wc, self.R_
                )
                R = huber_noise(self.R_, y - predicted, S, kalman_filter.threshold)
            kalman_filter.update(y, R=R)
        return kalman_filter.x.copy()
