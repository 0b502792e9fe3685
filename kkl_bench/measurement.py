"""How a task observes the state: the sensor, the sampling and the noise law (protocol 7.6).

The protocol's measurement is ``y_k = h(x_k) + v_k`` at every sample with
``v_k ~ N(0, sigma_v^2 I)``. A track task may declare another
:class:`MeasurementModel`:

* a **sensor**, a registered elementwise function ``s`` of the system's output:
  the measurement is ``s(h(x)) + v`` (:data:`sensors`: ``identity``,
  ``saturating``, ``quantized``; plugins add more through the
  ``kkl_bench.sensors`` entry-point group);
* a **sampling**: with ``observe_every = k`` the measurement is present at
  samples ``0, k, 2k, ...`` and NaN in between (scores still use every sample);
* a **noise law** (:class:`NoiseLaw`): Gaussian, Student-t, or Gaussian with a
  fraction of outliers.

:meth:`MeasurementModel.system` gives the model with the sensor in its ``h``
(and ``h_jacobian``), so filters and data generators need no other change;
:meth:`MeasurementModel.log_density` is the exact density a particle filter
weights with, and :attr:`MeasurementModel.variance` the variance a Gaussian
filter uses for ``R``.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numba
import numpy as np
from scipy import special

from kkl_bench.protocol import SIGMA_V, compiled
from kkl_bench.protocol.system import ReadThrough, System
from kkl_bench.registry import Registry

sensors: Registry = Registry("sensor", "kkl_bench.sensors")

FEATURES = ("sensor", "sampling", "noise")
"""The aspects in which a measurement model can differ from the protocol's; an estimator
lists those it handles in ``Estimator.supported_measurements``."""


def _math(value: Any):
    """numpy, or torch when ``value`` is a tensor (sensors run inside learned models too)."""
    if isinstance(value, np.ndarray | float | int):
        return np
    import torch  # only reached when the caller passes tensors

    return torch


class Sensor(ABC):
    """An elementwise function ``s`` of the system's output ``h(x)``.

    Subclasses are frozen dataclasses whose fields are the sensor's parameters.

    Attributes
    ----------
    name: the registry name.
    added_variance: variance a Gaussian filter adds to ``R`` for what the sensor loses
        (0 but for the quantizer).
    reads_as_noise: whether a Gaussian filter may leave the sensor out of its model and
        read what it loses as additive noise of ``added_variance`` (the classical model of
        quantization; :func:`filter_system`).
    """

    name: ClassVar[str]
    reads_as_noise: ClassVar[bool] = False

    @abstractmethod
    def __call__(self, output):
        """``s(output)``, elementwise; ``output: (..., n_y)`` array or tensor."""

    @abstractmethod
    def slope(self, output: np.ndarray) -> np.ndarray:
        """``ds/d(output)`` elementwise, ``(..., n_y)``: what a linearizing filter uses."""

    @property
    def added_variance(self) -> float:
        return 0.0

    def compiled(self) -> tuple | None:
        """``(sense, sense_slope, s)``: the sensor as numba functions and its parameters
        (:class:`kkl_bench.protocol.compiled.CompiledModel`), or None (the default) if it
        has no compiled form; the filters then run their reference engine."""
        return None

    def describe(self) -> str:
        params = ", ".join(f"{f.name} {getattr(self, f.name):g}" for f in dataclasses.fields(self))
        return f"{self.name} ({params})" if params else self.name


@sensors.register("identity")
@dataclass(frozen=True)
class Identity(Sensor):
    """The system's own output: ``s(h) = h``."""

    name: ClassVar[str] = "identity"

    def __call__(self, output):
        return output

    def slope(self, output):
        return np.ones_like(output)

    def compiled(self):
        return compiled.no_sensor, compiled.unit_slope, np.zeros(0)


@sensors.register("saturating")
@dataclass(frozen=True)
class Saturating(Sensor):
    """A sensor that saturates smoothly at ``+/- limit``: ``s(h) = limit tanh(h / limit)``."""

    name: ClassVar[str] = "saturating"
    limit: float = 1.0

    def __post_init__(self) -> None:
        if not self.limit > 0:
            raise ValueError(f"saturating sensor: limit={self.limit!r} must be positive")

    def __call__(self, output):
        return self.limit * _math(output).tanh(output / self.limit)

    def slope(self, output):
        return 1.0 - np.tanh(output / self.limit) ** 2

    def compiled(self):
        return _saturate, _saturation_slope, np.array([self.limit])


@numba.njit(cache=True)
def _saturate(h, s):
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            h[i, j] = s[0] * np.tanh(h[i, j] / s[0])


@numba.njit(cache=True)
def _saturation_slope(h, s, out):
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            out[i, j] = 1.0 - np.tanh(h[i, j] / s[0]) ** 2


@sensors.register("quantized")
@dataclass(frozen=True)
class Quantized(Sensor):
    """An analog-to-digital converter with resolution ``step``: ``s(h) = step round(h / step)``.

    Its derivative is zero almost everywhere; linearizing filters use the slope of its
    mean response (1) and add the quantization error's variance ``step^2 / 12`` to ``R``
    (the classical model of quantization as uniform noise).
    """

    name: ClassVar[str] = "quantized"
    reads_as_noise: ClassVar[bool] = True
    step: float = 0.1

    def __post_init__(self) -> None:
        if not self.step > 0:
            raise ValueError(f"quantized sensor: step={self.step!r} must be positive")

    def __call__(self, output):
        return self.step * _math(output).round(output / self.step)

    def slope(self, output):
        return np.ones_like(output)

    def compiled(self):
        return _quantize, compiled.unit_slope, np.array([self.step])

    @property
    def added_variance(self) -> float:
        return self.step**2 / 12.0


@numba.njit(cache=True)
def _quantize(h, s):
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            h[i, j] = s[0] * np.rint(h[i, j] / s[0])  # numpy's round: half to even


NOISE_LAWS = ("gaussian", "student-t", "outliers")


@dataclass(frozen=True)
class NoiseLaw:
    """The law of each component of the measurement noise ``v_k`` (independent components).

    Attributes
    ----------
    law: ``"gaussian"``: ``sigma z``; ``"student-t"``: ``sigma t_dof`` (heavy tails; its
        variance is ``sigma^2 dof / (dof - 2)`` for ``dof > 2``); ``"outliers"``: ``sigma z``,
        times ``outlier_scale`` with probability ``outlier_fraction``.
    sigma: the scale, ``measurement_noise`` in a track file.
    dof: Student-t degrees of freedom.
    outlier_fraction, outlier_scale: the outliers' probability and size (in ``sigma``).
    """

    law: str = "gaussian"
    sigma: float = SIGMA_V
    dof: float = 3.0
    outlier_fraction: float = 0.05
    outlier_scale: float = 10.0

    def __post_init__(self) -> None:
        if self.law not in NOISE_LAWS:
            raise ValueError(f"unknown noise law {self.law!r}; valid laws: {', '.join(NOISE_LAWS)}")
        if not self.sigma >= 0:
            raise ValueError(f"noise law: sigma={self.sigma!r} must be non-negative")
        if self.law == "student-t" and not self.dof > 2:
            raise ValueError(f"student-t noise: dof={self.dof!r} must exceed 2 (finite variance)")
        if self.law == "outliers" and not (
            0 <= self.outlier_fraction < 1 and self.outlier_scale >= 1
        ):
            raise ValueError(
                f"outlier noise: outlier_fraction={self.outlier_fraction!r} must be in [0, 1) "
                f"and outlier_scale={self.outlier_scale!r} at least 1"
            )

    @property
    def gaussian(self) -> bool:
        return self.law == "gaussian"

    @property
    def variance(self) -> float:
        """The variance of each component."""
        if self.law == "student-t":
            return self.sigma**2 * self.dof / (self.dof - 2.0)
        if self.law == "outliers":
            return self.sigma**2 * (1.0 + self.outlier_fraction * (self.outlier_scale**2 - 1.0))
        return self.sigma**2

    @property
    def mixture(self) -> tuple[tuple[float, float], ...] | None:
        """``((weight, variance), ...)`` of each component when the law is a finite mixture
        of zero-mean Gaussians with more than one component (the outlier law), else None."""
        if self.law != "outliers" or self.outlier_fraction == 0:
            return None
        fraction, scale = self.outlier_fraction, self.outlier_scale
        return ((1.0 - fraction, self.sigma**2), (fraction, (scale * self.sigma) ** 2))

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Noise of ``shape`` from ``rng`` (Gaussian: ``sigma * rng.standard_normal(shape)``,
        the protocol's draw, then, for the other laws, their extra draws)."""
        if self.law == "student-t":
            return self.sigma * rng.standard_t(self.dof, shape)
        noise = self.sigma * rng.standard_normal(shape)
        if self.law == "outliers":
            noise = (
                np.where(rng.random(shape) < self.outlier_fraction, self.outlier_scale, 1.0) * noise
            )
        return noise

    @property
    def student_t_log_norm(self) -> float:
        """``log`` of the Student-t law's normalizing constant at scale ``sigma``."""
        nu = self.dof
        return (
            special.gammaln((nu + 1) / 2)
            - special.gammaln(nu / 2)
            - 0.5 * math.log(nu * math.pi)
            - math.log(self.sigma)
        )

    def log_density(self, residual: np.ndarray) -> np.ndarray:
        """``log p(residual)`` summed over the last axis (``(..., n_y)`` -> ``(...)``)."""
        z = residual / self.sigma
        if self.law == "student-t":
            nu = self.dof
            each = self.student_t_log_norm - (nu + 1) / 2 * np.log1p(z**2 / nu)
        elif self.law == "outliers":
            p, s = self.outlier_fraction, self.outlier_scale
            inlier = math.log1p(-p) - 0.5 * z**2
            outlier = math.log(p) - math.log(s) - 0.5 * (z / s) ** 2 if p > 0 else -np.inf
            each = (
                np.logaddexp(inlier, outlier) - 0.5 * math.log(2 * math.pi) - math.log(self.sigma)
            )
        else:  # the particle filter's Gaussian log density since protocol v1, to the bit
            variance = self.sigma**2
            dim = residual.shape[-1]
            return -0.5 * (
                np.sum(residual**2, axis=-1) / variance + dim * np.log(2 * np.pi * variance)
            )
        return np.sum(each, axis=-1)

    def describe(self) -> str:
        if self.law == "student-t":
            return f"Student-t, {self.dof:g} dof, scale {self.sigma:g}"
        if self.law == "outliers":
            return (
                f"Gaussian {self.sigma:g}, {self.outlier_fraction:.0%} outliers "
                f"x{self.outlier_scale:g}"
            )
        return f"Gaussian {self.sigma:g}"


@dataclass(frozen=True)
class MeasurementModel:
    """How a task's states are observed (see the module docstring).

    Attributes
    ----------
    sensor: the sensor applied to the system's output.
    observe_every: the measurement is present every ``observe_every``-th sample.
    noise: the law of the measurement noise.
    """

    sensor: Sensor = field(default_factory=Identity)
    observe_every: int = 1
    noise: NoiseLaw = field(default_factory=NoiseLaw)

    def __post_init__(self) -> None:
        if (
            not isinstance(self.observe_every, int)
            or isinstance(self.observe_every, bool)
            or self.observe_every < 1
        ):
            raise ValueError(
                f"observe_every={self.observe_every!r} must be a positive integer (1: every sample)"
            )

    @property
    def sigma(self) -> float:
        """The noise law's scale (``FitContext.sigma_v``)."""
        return self.noise.sigma

    @property
    def features(self) -> frozenset[str]:
        """The :data:`FEATURES` in which this model is not the protocol's."""
        return frozenset(
            name
            for name, differs in (
                ("sensor", not isinstance(self.sensor, Identity)),
                ("sampling", self.observe_every != 1),
                ("noise", not self.noise.gaussian),
            )
            if differs
        )

    @property
    def variance(self) -> float:
        """What a Gaussian filter takes as each output's noise variance: the law's, plus
        what the sensor loses (:attr:`Sensor.added_variance`)."""
        return self.noise.variance + self.sensor.added_variance

    @property
    def inlier_variance(self) -> float:
        """What a robust filter takes as each output's noise variance: the law's scale
        squared (the inliers' variance under the outlier law, the Student-t scale's square),
        plus what the sensor loses; :attr:`variance` for the Gaussian law."""
        return self.noise.sigma**2 + self.sensor.added_variance

    @property
    def mixture(self) -> tuple[tuple[float, float], ...] | None:
        """The noise law's Gaussian components ``((weight, variance), ...)`` as a filter
        takes them, each variance plus what the sensor loses (as :attr:`variance`); None
        unless the law is a mixture (:attr:`NoiseLaw.mixture`)."""
        if self.noise.mixture is None:
            return None
        added = self.sensor.added_variance
        return tuple((weight, variance + added) for weight, variance in self.noise.mixture)

    def cache_entry(self) -> dict[str, str]:
        """What a trained model's cache description adds for this measurement model: nothing
        for the protocol's (the keys of models trained before it existed stay valid)."""
        return {} if self == MeasurementModel() else {"measurement": repr(self)}

    def system(self, model: System) -> System:
        """``model`` read through the sensor (``model`` itself for the identity sensor)."""
        if isinstance(self.sensor, Identity):
            return model
        return SensedSystem(model, self.sensor)

    def observed(self, steps: int) -> np.ndarray:
        """``(steps,)`` whether each sample's measurement is present."""
        return np.arange(steps) % self.observe_every == 0

    def measure(self, output: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """The measurements ``(batch, steps, n_y)`` from the sensed outputs (the sensed
        system's ``h(x)``) and the noise, NaN at the samples not observed."""
        y = output + noise
        if self.observe_every != 1:
            y = np.where(self.observed(y.shape[1])[:, None], y, np.nan)
        return y

    def log_density(self, y: np.ndarray, output: np.ndarray) -> np.ndarray:
        """``log p(y | x)`` for the sensed outputs ``output = h(x)``, summed over the last axis."""
        return self.noise.log_density(y - output)

    def describe(self) -> str:
        parts = [f"sensor {self.sensor.describe()}"] if "sensor" in self.features else []
        if self.observe_every != 1:
            parts.append(f"every {self.observe_every} samples")
        return ", ".join([*parts, f"noise {self.noise.describe()}"])


def held(y: np.ndarray) -> np.ndarray:
    """The measurements with the last one held over the samples that have none.

    The zero-order hold a digital observer running faster than its sensor applies
    (the learned rows' reading of a sparse sampling, protocol 7.6). ``y: (batch,
    steps, n_y)``, NaN where not observed; returns the same shape, ``y`` itself when
    every sample is present. Samples before a trajectory's first measurement stay NaN
    (every sampling here observes sample 0).
    """
    missing = np.isnan(y)
    if not missing.any():
        return y
    last = np.where(missing, 0, np.arange(y.shape[1])[:, None])
    np.maximum.accumulate(last, axis=1, out=last)
    return np.take_along_axis(y, last, axis=1)


def filter_system(system: System, measurement: MeasurementModel) -> System:
    """The model a Gaussian filter reading ``measurement`` runs: ``system`` (the task's,
    its sensor in ``h``), or the model without the sensor where the sensor reads as
    additive noise (:attr:`Sensor.reads_as_noise`: a quantizer), whose loss is then in
    :attr:`MeasurementModel.variance`."""
    if measurement.sensor.reads_as_noise and isinstance(system, SensedSystem):
        return system.model
    return system


def with_scale(
    measurement: MeasurementModel | None, sigma_v: float, owner: str
) -> MeasurementModel:
    """``measurement``, or the protocol's with noise scale ``sigma_v`` if None; a model whose
    scale is not ``sigma_v`` is refused (``owner`` names what declared both)."""
    if measurement is None:
        return MeasurementModel(noise=NoiseLaw(sigma=sigma_v))
    if measurement.sigma != sigma_v:
        raise ValueError(
            f"{owner}: the measurement model's noise scale {measurement.sigma!r} is not "
            f"sigma_v {sigma_v!r}"
        )
    return measurement


class SensedSystem(ReadThrough):
    """A system whose output is a sensor's reading of another system's: ``s(h(x))``."""

    def __init__(self, model: System, sensor: Sensor) -> None:
        super().__init__(model)
        self.sensor = sensor

    def h(self, x):
        return self.sensor(self.model.h(x))

    def h_jacobian(self, x):
        slope = self.sensor.slope(self.model.h(x))
        return slope[..., :, None] * self.model.h_jacobian(x)

    def compiled(self):
        model, sensor = self.model.compiled(), self.sensor.compiled()
        if model is None or sensor is None:
            return None
        sense, sense_slope, s = sensor
        return dataclasses.replace(model, sense=sense, sense_slope=sense_slope, s=s)
