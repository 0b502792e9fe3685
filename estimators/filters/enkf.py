"""Ensemble transform Kalman filter (a square-root EnKF) on the exact discrete-time model.

The analysis is the ETKF of Bishop, Etherton and Majumdar (Mon. Wea. Rev. 129,
2001) in the symmetric square-root form of Hunt, Kostelich and Szunyogh
(Physica D 230, 2007), computed in the ensemble space of ``N`` members. With
forecast anomalies ``A = X - x_bar`` (``N x n``), ``Y_b`` the anomalies of
``h`` over the members and ``C = Y_b R^-1``:

    P_a = [(N - 1) I + C Y_b^T]^-1,        w_bar = P_a C (y - y_bar),
    W_a = [(N - 1) P_a]^(1/2) (symmetric), X_a = x_bar + (w_bar + W_a)^T A,

so the analysis mean and covariance are the Kalman filter's for the ensemble's
Gaussian, and the anomalies stay centred. After each analysis the anomalies
are multiplied by ``inflation`` (multiplicative inflation of the posterior,
the convention of DAPPER's ``EnKF('Sqrt', infl=...)``). By default the
inflation is tuned per system like every other row's free choices: the one
of :data:`INFLATIONS` with the lowest RMSE over the scored window of forced
validation trajectories of a training stream (never a test stream), simulated
by the model it filters with (the calibrated one for ``enkf+logged``). Each
member is then propagated by the protocol's transition: the RK4 step with the held input,
process noise ``N(0, sigma_w^2 I)`` and the system's constraint, as the truth
is. A sample whose measurement is missing (NaN) is a forecast only. On a task with
another measurement model the members are read through its sensor (``system.h``),
but for a quantizer, which may be read as additive noise (``quantizer='noise'``: ``h``
without it; ``'in-model'`` keeps it in ``h``, where members that share one quantization
cell predict one measurement and the update vanishes; ``'auto'``, the default, chooses
between the two with the inflation), and ``R`` is the
noise law's variance (plus a quantizer's ``step^2 / 12``). The analysis stays the
Gaussian one under heavy-tailed noise (the robust update is the EKF's and the UKF's,
``kkl_bench.estimators.filters.kalman``).

The first ensemble is drawn from the uniform x0 box, the protocol's prior.
Every trajectory draws from its own generator (seed and first measurement),
so estimates are causal, batch-independent and reproducible. The estimate is the
analysis mean.

Two engines run the same filter (``engine=``, as for the EKF and the UKF,
:mod:`kkl_bench.estimators.filters.kalman`): ``"reference"`` (the default, what the published
cells come from), numpy vectorised over members and trajectories, and ``"compiled"``,
the same arithmetic in a numba kernel over the system's compiled model
(:mod:`kkl_bench.estimators.filters.enkf_kernels`), fed the same random numbers; a system
without a compiled model runs the reference engine. The validation runs that choose
the inflation and the quantizer's treatment run on the row's own engine (numba compiles
the kernel once per system and process, which takes tens of seconds; the reference
engine's choices are then exactly the published cells').
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from kkl_bench.estimators.filters import enkf_kernels, traced_transition
from kkl_bench.estimators.filters.kalman import (
    QUANTIZERS,
    TwoEngines,
    check_choice,
    check_engine,
    treatment_settings,
    treatment_systems,
)
from kkl_bench.estimators.filters.monte_carlo import trajectory_generators

from kkl_bench.estimator import Estimator
from kkl_bench.fitting.calibration import CalibratesOnLoggedData
from kkl_bench.fitting.tuning import choose, validation_data
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.protocol.system import Ring, System
from kkl_bench.registry import estimators
from kkl_bench.support.kernel_cache import bind


def transform(forecast: np.ndarray, predicted: np.ndarray, y: np.ndarray, r: float) -> np.ndarray:
    """The ETKF analysis ensemble ``(batch, N, n_x)``.

    ``forecast: (batch, N, n_x)`` members, ``predicted: (batch, N, n_y)`` their ``h``,
    ``y: (batch, n_y)`` the measurements, ``r`` the measurement noise variance.
    """
    members = forecast.shape[1]
    mean = forecast.mean(axis=1, keepdims=True)
    anomalies = forecast - mean
    predicted_mean = predicted.mean(axis=1, keepdims=True)
    predicted_anomalies = predicted - predicted_mean  # Y_b^T: (batch, N, n_y)
    scaled = predicted_anomalies / r  # C^T with R = r I
    precision = (members - 1) * np.eye(members) + scaled @ predicted_anomalies.transpose(0, 2, 1)
    values, vectors = np.linalg.eigh(precision)  # symmetric positive definite
    innovation = y[:, None, :] - predicted_mean  # (batch, 1, n_y)
    # w_bar = P_a C (y - y_bar), as a row (batch, 1, N)
    projected = innovation @ scaled.transpose(0, 2, 1)  # (batch, 1, N)
    weights = ((projected @ vectors) / values[:, None, :]) @ vectors.transpose(0, 2, 1)
    root = (vectors * np.sqrt((members - 1) / values)[:, None, :]) @ vectors.transpose(0, 2, 1)
    return mean + (weights + root) @ anomalies  # W_a is symmetric


class LocalTaper(NamedTuple):
    """A taper restricted to the measurements each site weighs: ``near: (sites, m)``
    their indices, ``weights: (sites, m)`` their weights (``m`` the most any site weighs;
    shorter rows padded with zero weights)."""

    near: np.ndarray
    weights: np.ndarray

    @classmethod
    def of(cls, taper: np.ndarray) -> LocalTaper:
        """From the full ``(sites, n_y)`` weights in [0, 1]."""
        near = np.argsort(-taper, axis=1, kind="stable")[:, : int((taper > 0).sum(axis=1).max())]
        return cls(near, np.take_along_axis(taper, near, axis=1))


def local_transform(
    forecast: np.ndarray, predicted: np.ndarray, y: np.ndarray, r: float, taper: LocalTaper
) -> np.ndarray:
    """The LETKF analysis ensemble ``(batch, N, n_x)``: every site's states take the
    weights of an ETKF analysis of their own, in which measurement ``j`` has the
    precision ``taper[s, j] / r`` (Hunt, Kostelich and Szunyogh 2007, section 2.3, with
    the observation error inflated away from the site, "R-localization").

    ``forecast: (batch, N, n_x)`` members with ``n_x = sites k`` states in site-major
    order, ``predicted: (batch, N, n_y)`` their ``h``, ``y: (batch, n_y)``, ``r`` the
    measurement noise variance, ``taper`` the weights (:meth:`LocalTaper.of`; each site's
    analysis reads only the measurements it weighs). With every weight 1 it is
    :func:`transform`.
    """
    batch, members, n_x = forecast.shape
    near, local_taper = taper
    sites = near.shape[0]
    mean = forecast.mean(axis=1, keepdims=True)
    anomalies = forecast - mean
    predicted_mean = predicted.mean(axis=1, keepdims=True)
    predicted_anomalies = (predicted - predicted_mean)[:, :, near].transpose(0, 2, 1, 3)
    scaled = predicted_anomalies * (local_taper / r)[None, :, None, :]  # (batch, sites, N, m)
    precision = (members - 1) * np.eye(members) + scaled @ predicted_anomalies.swapaxes(-1, -2)
    values, vectors = np.linalg.eigh(precision)  # (batch, sites, N), (batch, sites, N, N)
    innovation = (y - predicted_mean[:, 0])[:, near][:, :, None, :]  # (batch, sites, 1, m)
    projected = innovation @ scaled.swapaxes(-1, -2)  # (batch, sites, 1, N)
    weights = ((projected @ vectors) / values[..., None, :]) @ vectors.swapaxes(-1, -2)
    root = (vectors * np.sqrt((members - 1) / values)[..., None, :]) @ vectors.swapaxes(-1, -2)
    local = anomalies.reshape(batch, members, sites, -1).transpose(0, 2, 1, 3)  # (b, s, N, k)
    updated = (weights + root) @ local
    return mean + updated.transpose(0, 2, 1, 3).reshape(batch, members, n_x)


def gaspari_cohn(distance: np.ndarray, half_width: float) -> np.ndarray:
    """Gaspari and Cohn's compactly supported correlation function (Q. J. R. Meteorol.
    Soc. 125, 1999, eq. 4.10) at ``distance``: 1 at 0, 0 from ``2 half_width`` on."""
    z = np.abs(np.asarray(distance, dtype=float)) / half_width
    near = (((-0.25 * z + 0.5) * z + 0.625) * z - 5 / 3) * z**2 + 1
    with np.errstate(divide="ignore"):
        far = ((((z / 12 - 0.5) * z + 0.625) * z + 5 / 3) * z - 5) * z + 4 - 2 / (3 * z)
    return np.where(z <= 1, near, np.where(z < 2, far, 0.0))


def ring_taper(ring: Ring, half_width: float) -> np.ndarray:
    """``(sites, n_y)``: the Gaspari-Cohn weight of each output for each site, by the
    distance along the ring between the site and the output's site."""
    sites = np.arange(ring.sites)[:, None]
    apart = np.abs(sites - np.asarray(ring.output_sites)[None, :])
    return gaspari_cohn(np.minimum(apart, ring.sites - apart), half_width)


def analysis_flops(members: int, outputs: int, states: int, low_rank: bool) -> int:
    """Flops of one ETKF analysis of ``states`` states over ``outputs`` measurements, from
    the anomalies to the analysis members: with the ``N x N`` eigendecomposition (counted
    as ``9 N^3``) and transform of :func:`transform`, or, ``low_rank``, with the ``m x m``
    one of the compiled engine (:func:`kkl_bench.estimators.filters.enkf_kernels._analyse`; none
    for one output)."""
    n, m, k = members, outputs, states
    scaled_and_projected = 3 * n * m
    if not low_rank:
        precision = 2 * n * n * m + n + 9 * n**3
        weights = 4 * n * n + n
        root = n * n + 2 * n**3 + n
        update = n * n + 2 * n * n * k + n * k
        return scaled_and_projected + precision + weights + root + update
    gram = n * m + m + 2 * n * m * m + (9 * m**3 if m > 1 else 0)
    rotated = 2 * n * m * m + 2 * n * m
    weights = 2 * n * m + 2 * m + n + 5 * m
    update = 2 * n * k + 2 * n * m * k + m * k + n * k * (1 + 2 * m)
    return scaled_and_projected + gram + rotated + weights + update


INFLATIONS = (1.0, 1.01, 1.02, 1.05, 1.1)
"""The inflations the default ``enkf`` chooses from."""


@estimators.register("enkf")
class EnsembleKalman(TwoEngines, CalibratesOnLoggedData, Estimator):
    """Ensemble transform (square-root) Kalman filter with multiplicative inflation.

    Parameters
    ----------
    n: ensemble members per trajectory (at least 2).
    inflation: factor on the analysis anomalies after each update (1: none), or None
        (default) to choose it per system on validation trajectories (see the module).
    localization: None (default) for the global analysis, or the half-width, in sites,
        of the Gaspari-Cohn taper of a local analysis per site (the LETKF,
        :func:`local_transform`; measurements 2 half-widths away or more are ignored);
        only on systems that declare a ring (``System.ring``).
    quantizer: ``"auto"`` (default: chosen on validation trajectories), ``"noise"`` (a
        quantizer read as additive noise) or ``"in-model"``.
    engine: ``"compiled"`` or ``"reference"`` (numpy; the module docstring).
    """

    name = "enkf"
    family = "model-based"
    supported_measurements = frozenset({"sensor", "sampling", "noise"})

    def __init__(
        self,
        n: int = 24,
        inflation: float | None = None,
        localization: float | None = None,
        quantizer: str = "auto",
        engine: str = "reference",
    ) -> None:
        self.n = n
        self.inflation = inflation
        self.localization = localization
        self.quantizer = quantizer
        self.engine = engine
        check_choice("enkf", "quantizer", quantizer, QUANTIZERS)
        check_engine("enkf", engine)
        if localization is not None and not (
            isinstance(localization, int | float) and localization > 0
        ):
            raise ValueError(
                f"enkf: localization={localization!r} must be a positive half-width in "
                "sites, or None"
            )
        if not (isinstance(n, int) and n >= 2):
            raise ValueError(f"enkf: n={n!r} must be an integer of at least 2")
        if inflation is not None and not (isinstance(inflation, int | float) and inflation >= 1):
            raise ValueError(
                f"enkf: inflation={inflation!r} must be a number of at least 1, or None"
            )

    def unsupported_reason(self, system, measurement):
        if self.localization is not None and system.ring is None:
            return (
                f"localizes along a ring (System.ring), and {system.name} declares none; "
                "the global enkf runs there"
            )
        return super().unsupported_reason(system, measurement)

    def fit(self, context):
        context = super().fit(context).check_fitted()  # the calibrated model, given logged data
        self.taper_ = (
            None
            if self.localization is None
            else LocalTaper.of(ring_taper(context.system.ring, self.localization))
        )
        systems_ = treatment_systems(self.quantizer, context.system, context.measurement)
        treatments = treatment_settings(systems_, context.measurement)
        inflations = INFLATIONS if self.inflation is None else (self.inflation,)
        candidates = [{**t, "inflation": a} for t in treatments for a in inflations]

        def choose_setting(setting):
            self.system_ = systems_[setting.get("quantizer", "in-model")]
            self.inflation_ = setting["inflation"]
            self.model_ = self.system_.compiled() if self.engine == "compiled" else None

        self.scores_ = {}
        self.setting_ = candidates[0]
        if len(candidates) > 1:

            def estimate(setting, data):
                choose_setting(setting)
                return self.estimate(data.t, data.y, data.u)

            data = validation_data(context.training, "enkf/validation")
            self.setting_, self.scores_ = choose(candidates, estimate, data)
        choose_setting(self.setting_)
        return self

    def fit_report(self):
        return {
            **super().fit_report(),
            "engine": self.engine_used,
            "members": self.n,
            **({"localization": self.localization} if self.localization is not None else {}),
            "inflation": self.inflation_,
            **({"selection": self.scores_} if self.scores_ else {}),
            **({"quantizer": self.setting_["quantizer"]} if "quantizer" in self.setting_ else {}),
        }

    def flops_per_step(self) -> float:
        """Flops of one trajectory-step on the engine that runs: every member's RK4 step and
        noise, the analysis (per site with localization, over the measurements the site
        weighs, :func:`analysis_flops`) and the inflation. NaN for a system without a
        compiled model (no declared drift count)."""
        model = self.system_.compiled()
        if model is None:
            return math.nan
        members, n, m = self.n, model.n_x, model.n_y
        if self.taper_ is None:
            sites, outputs = 1, m
        else:
            sites, outputs = self.taper_.near.shape
        forecast = members * (model.step_flops + 2 * n)
        means = 2 * members * n + 2 * members * m + m
        low_rank = self.engine_used == "compiled" and outputs < members
        analyses = sites * analysis_flops(members, outputs, n // sites, low_rank)
        inflation = 2 * members * n + n
        return float(forecast + means + analyses + inflation)

    def operations_per_step(self) -> dict[str, float]:
        """What one trajectory-step must draw besides its flops (protocol 6.3): every
        member's ``n_x`` standard normal numbers of process noise (none without it); the
        analysis's square roots are counted as flops."""
        context = self.check_fitted()
        noisy = context.sigma_w != 0
        return {"normal": self.n * self.system_.n_x * noisy, "uniform": 0, "transcendental": 0}

    def estimate(self, t, y, u):
        context = self.check_fitted()
        dt = float(t[1] - t[0]) if len(t) > 1 else context.dt
        if self.model_ is not None:
            return self._estimate_compiled(self.model_, dt, y, u)
        system = self.system_
        generators = trajectory_generators(context.seed, y[:, 0])
        batch, steps, _ = y.shape
        x_hat = np.full((batch, steps, system.n_x), np.nan)
        ensemble = np.stack(
            [
                rng.uniform(context.x0_low, context.x0_high, (self.n, system.n_x))
                for rng in generators
            ]
        )
        with np.errstate(over="ignore", invalid="ignore"):
            for k in range(steps):
                if k > 0:
                    ensemble = self._forecast(system, ensemble, u[:, k - 1], dt, generators)
                ensemble = self._analysis(system, ensemble, y[:, k])
                x_hat[:, k] = ensemble.mean(axis=1)
        # a trajectory whose ensemble blew up stays NaN from then on
        return np.where(
            (~np.isfinite(x_hat)).any(axis=-1, keepdims=True).cumsum(axis=1) > 0, np.nan, x_hat
        )

    def _estimate_compiled(self, model, dt: float, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`estimate` on the compiled kernel: one call a trajectory, which draws from
        the trajectory's generator the numbers the reference engine draws (the first
        ensemble, then every step's process noise)."""
        context = self.check_fitted()
        batch, steps, _ = y.shape
        x_hat = np.full((batch, steps, model.n_x), np.nan)
        if self.taper_ is None:
            near, taper = np.zeros((0, 0), dtype=np.int64), np.zeros((0, 0))
        else:
            near, taper = self.taper_.near.astype(np.int64), self.taper_.weights
        low, high = (
            np.asarray(bound, dtype=np.float64) for bound in (context.x0_low, context.x0_high)
        )
        y, u = self.kernel_inputs(y, u)
        transition = traced_transition.transition(model)
        etkf = bind(
            enkf_kernels.etkf, model.drift, model.output, model.sense, model.constrain,
            enkf_kernels.untraced if transition is None else transition,
        )  # fmt: skip
        for b, rng in enumerate(trajectory_generators(context.seed, y[:, 0])):
            etkf(
                model.p, model.q, model.s, model.g, transition is not None, rng, y[b], u[b], dt,
                float(context.sigma_w), float(context.measurement.variance),
                float(self.inflation_), near, taper, low, high, self.n, x_hat[b],
            )  # fmt: skip
        return x_hat

    def _forecast(
        self, system: System, ensemble: np.ndarray, u: np.ndarray, dt: float, generators
    ) -> np.ndarray:
        """Every member through the protocol's transition (``u: (batch, 1)``)."""
        sigma_w = self.check_fitted().sigma_w
        mean = rk4_step(system, ensemble, np.broadcast_to(u, ensemble.shape[:2]), dt)
        if sigma_w == 0:
            return system.constrain(mean)
        noise = np.stack([rng.standard_normal(ensemble.shape[1:]) for rng in generators])
        return system.constrain(mean + sigma_w * noise)

    def _analysis(self, system: System, ensemble: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The inflated analysis of the trajectories whose measurement ``y: (batch, n_y)``
        is present; the others keep their forecast (as does an ensemble that blew up: its
        estimate is NaN from then on)."""
        observed = np.isfinite(y).all(axis=-1) & np.isfinite(ensemble).all(axis=(1, 2))
        if not observed.any():
            return ensemble
        updated = ensemble.copy()
        arguments = (
            ensemble[observed],
            system.h(ensemble[observed]),
            y[observed],
            self.check_fitted().measurement.variance,
        )
        if self.taper_ is None:
            analysis = transform(*arguments)
        else:
            analysis = local_transform(*arguments, self.taper_)
        mean = analysis.mean(axis=1, keepdims=True)
        updated[observed] = mean + self.inflation_ * (analysis - mean)
        return updated
