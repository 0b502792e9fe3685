"""What the EKF and UKF baselines share: the protocol's prior, their design for the task's
sensor, and the filtering loop.

Both filters run the protocol's discrete-time model: the RK4 step with the
known held input as transition, followed by the system's constraint (erratum E1:
Rossler's ``x3`` reflected at 0, as the plant and the particle filter apply it),
``Q = sigma_w^2 I`` (the process noise is added after each step),
``R = sigma_v^2 I``, and an initial estimate at the centre of the x0 box with the
covariance of the uniform box distribution, ``diag((high - low)^2 / 12)``.

On a task with another measurement model (:mod:`kkl_bench.measurement`, the ``hard``
track) each filter is built for the task's sensor, as the literature builds it
(protocol 7.6):

* it updates only where ``y`` is present;
* a quantizer is read as additive uniform noise (``quantizer='noise'``: ``h`` without
  the quantizer, ``R`` plus ``step^2 / 12``) or kept in ``h`` (``'in-model'``, under
  which the UKF's sigma points often share one quantization cell and the gain
  vanishes); ``'auto'``, the default, chooses between the two;
* under a heavy-tailed noise law (``robust='auto'``, the default; ``'huber'`` always,
  ``'none'`` never) the update is Huber's: ``R`` is the inliers' variance
  (:attr:`~kkl_bench.measurement.MeasurementModel.inlier_variance`) and each output's
  variance is divided by its weight ``min(1, c / |e|)``, ``e`` the innovation over its
  predicted standard deviation (:func:`huber_noise`); ``c`` is ``threshold``, or chosen
  from :data:`THRESHOLDS`;
* the propagated covariance is inflated, ``P = a F P F^T + Q``, by ``inflation``, or by
  an ``a`` chosen from :data:`INFLATIONS`.

Choices left open (``quantizer='auto'``, ``threshold=None``, ``inflation=None``) are made
per fit on validation trajectories of the training stream (:mod:`kkl_bench.fitting.tuning`; as many
as the profile's ``filter_validation_trajectories``, 16 where it does not say), never a
test stream, and recorded in the fit report; on the protocol's measurement model the filter
is the plain one (inflation 1, no robust update), so the paper's cells are unchanged.

Two engines run the same filter (``engine=`` of both estimators): ``"reference"`` (the
default, what the published accuracy cells come from), filterpy's filter advanced one
trajectory and one sample at a time in Python, and ``"compiled"``, the same arithmetic
in numba kernels (:mod:`kkl_bench.estimators.filters.kalman_kernels`) over the system's compiled
model: what ``kkl-bench cost`` times as the row's online cost, with the reference beside
it (protocol 6.3). A system without a compiled model
(:meth:`~kkl_bench.protocol.system.System.compiled` is None: a plugin's) runs the
reference engine; the fit report names the engine that runs. The validation runs that
choose the settings use the compiled engine where the system has one (the same filter to
rounding; thousands of times faster than filterpy's loop).
"""

from __future__ import annotations

import math
from abc import abstractmethod
from typing import Any

import numpy as np

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.fitting.calibration import CalibratesOnLoggedData
from kkl_bench.fitting.tuning import VALIDATION_TRAJECTORIES, choose, validation_data
from kkl_bench.measurement import filter_system
from kkl_bench.protocol.compiled import CompiledModel
from kkl_bench.protocol.system import System

ENGINES = ("compiled", "reference")
"""The engines a model-based filter runs on (the module docstring)."""
ROBUST = ("auto", "huber", "none")
"""The update a filter makes (``robust=``): Huber's where the noise law is heavy-tailed,
always, or never."""
QUANTIZERS = ("auto", "noise", "in-model")
"""How a filter reads a quantizer (``quantizer=``): as additive noise, inside ``h``, or
(``auto``) the one of the two that does better on validation streams."""
THRESHOLDS = (0.5, 1.0, 1.345, 2.0, 3.0)
"""Huber thresholds ``c`` (in predicted standard deviations) a robust filter chooses from;
1.345 is Huber's classical choice (95 % efficiency under Gaussian noise)."""
INFLATIONS = (1.0, 1.02, 1.05, 1.1, 1.2)
"""Covariance inflations a filter chooses from off the protocol's measurement model."""
VALIDATION_STREAM = "filters/validation"


def check_choice(owner: str, key: str, value: object, valid: tuple[str, ...]) -> None:
    """Raise ``ValueError`` naming ``key=value`` and the valid values unless it is one."""
    if value not in valid:
        raise ValueError(f"{owner}: unknown {key}={value!r}; valid: {', '.join(valid)}")


def check_engine(owner: str, engine: object) -> None:
    """Raise ``ValueError`` naming ``engine`` and the valid ones unless it is one."""
    if engine not in ENGINES:
        raise ValueError(f"{owner}: unknown engine={engine!r}; valid engines: {', '.join(ENGINES)}")


def check_design(owner: str, robust, threshold, inflation, quantizer, engine) -> None:
    """Validate the hyperparameters every Kalman baseline shares (the module docstring)."""
    check_choice(owner, "robust", robust, ROBUST)
    check_choice(owner, "quantizer", quantizer, QUANTIZERS)
    check_engine(owner, engine)
    if threshold is not None and not (isinstance(threshold, int | float) and threshold > 0):
        raise ValueError(f"{owner}: threshold={threshold!r} must be a positive number, or None")
    if inflation is not None and not (isinstance(inflation, int | float) and inflation >= 1.0):
        raise ValueError(
            f"{owner}: inflation={inflation!r} must be a number of at least 1, or None"
        )


def treatment_systems(quantizer: str, system: System, measurement) -> dict[str, System]:
    """The model a filter runs under each treatment of the task's quantizer it considers
    when asked for ``quantizer``: ``{"in-model": system}`` (the sensor in ``h``, as every
    other sensor) unless the sensor reads as noise
    (:attr:`~kkl_bench.measurement.Sensor.reads_as_noise`); then the one asked for, or
    both for ``"auto"`` (``"noise"``: the model without the quantizer)."""
    if not measurement.sensor.reads_as_noise:
        treatments: tuple[str, ...] = ("in-model",)
    else:
        treatments = ("noise", "in-model") if quantizer == "auto" else (quantizer,)
    return {
        treatment: filter_system(system, measurement) if treatment == "noise" else system
        for treatment in treatments
    }


def treatment_settings(systems: dict[str, System], measurement) -> list[dict[str, str]]:
    """The ``quantizer`` entry of the settings to choose from, one per treatment of
    ``systems`` (:func:`treatment_systems`); none where the sensor does not read as noise."""
    if not measurement.sensor.reads_as_noise:
        return [{}]
    return [{"quantizer": treatment} for treatment in systems]


def huber_noise(R: np.ndarray, residual: np.ndarray, S: np.ndarray, threshold: float) -> np.ndarray:
    """``R (n_y, n_y)`` (diagonal) with each output's variance divided by its Huber weight
    ``min(1, threshold / e)``, ``e = |residual| / sqrt(S_jj)`` the innovation
    ``residual (n_y,)`` in predicted standard deviations (``S``: the innovation covariance
    with ``R``); ``R`` itself for an infinite threshold (the plain update)."""
    if not math.isfinite(threshold):
        return R
    with np.errstate(divide="ignore"):
        weights = np.minimum(1.0, threshold / (np.abs(residual) / np.sqrt(np.diag(S))))
    return np.diag(np.diag(R) / weights)


def box_prior(context: FitContext) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(n_x,)`` and covariance ``(n_x, n_x)`` of the uniform x0 box."""
    low, high = context.x0_low, context.x0_high
    return (low + high) / 2.0, np.diag((high - low) ** 2 / 12.0)


class TwoEngines:
    """What a model-based row with two engines (``engine=``) shares: ``model_``, set by its
    fit, is the compiled model its kernel runs, or None where the reference engine runs."""

    @property
    def engine_used(self) -> str:
        """The engine :meth:`estimate` runs: the one asked for, or ``"reference"`` where
        the system has no compiled model."""
        return "reference" if getattr(self, "model_", None) is None else "compiled"

    @staticmethod
    def kernel_inputs(y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``y: (batch, steps, n_y)`` and the input ``u: (batch, steps, 1)`` as the kernels
        take them: writeable, C-ordered float64 copies (``u`` without its last axis), since
        numba compiles a kernel anew for read-only arrays."""
        return (
            np.array(y, dtype=np.float64, order="C"),
            np.array(u[..., 0], dtype=np.float64, order="C"),
        )


class KalmanBaseline(TwoEngines, CalibratesOnLoggedData, Estimator):
    """A Kalman filter built for the task's sensor, on one of two engines (the module
    docstring).

    Subclasses store the shared hyperparameters (``robust``, ``threshold``,
    ``inflation``, ``quantizer``, ``engine``; :func:`check_design`), build the reference
    engine's filterpy filter (:meth:`make_filter`), take one of its predict-update steps
    (:meth:`step`), and run the compiled kernel (:meth:`run_compiled`). A fitted filter
    has ``system_``, the model it runs (the task's, or without a quantizer read as
    noise), ``R_ (n_y, n_y)`` and ``settings_``: ``threshold`` (Huber's ``c``; infinite
    for the plain update) and ``inflation``. A filter that hits a singular matrix yields
    NaN from there on, so the trajectory is reported as diverged. Nothing is trained, so
    the seed changes nothing: it is run once. Given logged data (``mismatch``), the filter
    runs on the model calibrated on them (:mod:`kkl_bench.fitting.calibration`).
    """

    family = "model-based"
    uses_seed = False
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    robust: str
    threshold: float | None
    inflation: float | None
    quantizer: str
    engine: str

    def store_design(self, **design: Any) -> None:
        """Store the hyperparameters every Kalman baseline shares (``inflation``, ``robust``,
        ``threshold``, ``quantizer``, ``engine``) under their names, once
        :func:`check_design` has accepted them."""
        check_design(self.name, **design)
        for key, value in design.items():
            setattr(self, key, value)

    def fit(self, context: FitContext):
        super().fit(context)
        fitted = self.check_fitted()
        measurement = fitted.measurement
        self.systems_ = treatment_systems(self.quantizer, fitted.system, measurement)
        robust = self.robust == "huber" or (
            self.robust == "auto" and not measurement.noise.gaussian
        )
        variance = measurement.inlier_variance if robust else measurement.variance
        self.R_ = variance * np.eye(fitted.system.n_y)
        candidates = self.candidates(
            robust, not measurement.features, treatment_settings(self.systems_, measurement)
        )
        self.selection_ = {}
        self.settings_ = candidates[0]
        if len(candidates) > 1:
            self.settings_, self.selection_ = choose(
                candidates,
                lambda settings, data: self.run(
                    self.filter_system(settings).compiled(), settings, data.t, data.y, data.u
                ),
                validation_data(
                    fitted.training,
                    VALIDATION_STREAM,
                    fitted.budget.get("filter_validation_trajectories", VALIDATION_TRAJECTORIES),
                ),
            )
        self.system_ = self.filter_system(self.settings_)
        self.model_ = self.system_.compiled() if self.engine == "compiled" else None
        return self

    def filter_system(self, settings: dict) -> System:
        """The model the filter runs with ``settings``: the task's, or without a quantizer
        read as noise."""
        return self.systems_[settings.get("quantizer", "in-model")]

    def candidates(
        self, robust: bool, plain: bool, treatments: list[dict[str, str]]
    ) -> list[dict[str, Any]]:
        """The settings to choose from: the quantizer's ``treatments``
        (:func:`treatment_settings`), ``threshold`` (infinite unless ``robust``) and ``inflation``, each
        the one given or, where left open, the grid (an inflation of 1 on the protocol's
        measurement model, ``plain``)."""
        if not robust:
            thresholds = (math.inf,)
        else:
            thresholds = THRESHOLDS if self.threshold is None else (float(self.threshold),)
        if self.inflation is not None:
            inflations = (float(self.inflation),)
        else:
            inflations = (1.0,) if plain else INFLATIONS
        return [
            {**treatment, "threshold": c, "inflation": a}
            for treatment in treatments
            for c in thresholds
            for a in inflations
        ]

    def fit_report(self) -> dict[str, Any]:
        context = self.check_fitted()
        threshold = self.settings_["threshold"]
        return {
            **super().fit_report(),
            "engine": self.engine_used,
            "update": "huber" if math.isfinite(threshold) else "gaussian",
            **({"huber_threshold": threshold} if math.isfinite(threshold) else {}),
            "inflation": self.settings_["inflation"],
            "noise_variance": float(self.R_[0, 0]),
            **(
                {"quantizer": self.settings_.get("quantizer", "in-model")}
                if context.measurement.sensor.reads_as_noise
                else {}
            ),
            **({"selection": self.selection_} if self.selection_ else {}),
        }

    def flops_per_step(self) -> float:
        """Floating-point operations of one trajectory-step (a predict and an update) on the
        fitted system, counted from the algorithm with dense matrices (NaN for a system
        without a compiled model, whose drift has no declared count)."""
        model = self.system_.compiled()
        return math.nan if model is None else float(self.count_flops(model))

    @abstractmethod
    def count_flops(self, model: CompiledModel) -> int:
        """Flops of one predict and one update on ``model`` with the fitted settings."""

    @abstractmethod
    def run_compiled(self, model: CompiledModel, settings: dict, dt: float, y, u, out) -> None:
        """Fill ``out: (batch, steps, n_x)`` (NaN on entry) from ``y: (batch, steps, n_y)``
        and ``u: (batch, steps)`` with the compiled kernel on ``model`` and ``settings``."""

    @abstractmethod
    def make_filter(self, settings: dict, dt: float):
        """A fresh filterpy filter at the box prior, with ``settings``."""

    @abstractmethod
    def step(self, kalman_filter, u_previous: float | None, y: np.ndarray) -> np.ndarray:
        """Predict with ``u_previous`` (None at k = 0), update with ``y: (n_y,)`` if it is
        present (not NaN); return the posterior mean ``(n_x,)``."""

    def estimate(self, t, y, u):
        self.check_fitted()
        return self.run(self.model_, self.settings_, t, y, u)

    def run(self, model: CompiledModel | None, settings: dict, t, y, u) -> np.ndarray:
        """The estimates ``(batch, steps, n_x)`` with ``settings``, on the compiled kernel of
        ``model``, or on the reference engine if ``model`` is None."""
        context = self.check_fitted()
        dt = float(t[1] - t[0]) if len(t) > 1 else context.dt
        batch, steps, _ = y.shape
        x_hat = np.full((batch, steps, context.system.n_x), np.nan)
        if model is not None:
            self.run_compiled(model, settings, dt, *self.kernel_inputs(y, u), x_hat)
            return x_hat
        for b in range(batch):
            kalman_filter = self.make_filter(settings, dt)
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

    def prior(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The box prior's mean ``(n_x,)`` and covariance, and ``Q (n_x, n_x)``."""
        context = self.check_fitted()
        mean, covariance = box_prior(context)
        return mean, covariance, context.sigma_w**2 * np.eye(context.system.n_x)
