"""A task's measurement model: its sensor, sampling and noise law, and the system read through it."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from kkl_bench.measurement.noise import NoiseLaw
from kkl_bench.measurement.sensing import Identity, Sensor
from kkl_bench.protocol.system import ReadThrough, System


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
        return dataclasses.replace(
            model,
            sense=sense,
            sense_slope=sense_slope,
            s=s,
            constant_output_jacobian=model.constant_output_jacobian and self.sensor.constant_slope,
        )
