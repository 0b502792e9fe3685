"""Sensors: elementwise functions of a system's output, registered by name (``kkl_bench.sensors``)."""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numba
import numpy as np

from kkl_bench.protocol import compiled
from kkl_bench.protocol.system import namespace
from kkl_bench.registry import Registry

sensors: Registry = Registry("sensor", "kkl_bench.sensors")

FEATURES = ("sensor", "sampling", "noise")
"""The aspects in which a measurement model can differ from the protocol's; an estimator
lists those it handles in ``Estimator.supported_measurements``."""


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
    constant_slope: whether :meth:`slope` is the same at every output.
    """

    name: ClassVar[str]
    reads_as_noise: ClassVar[bool] = False
    constant_slope: ClassVar[bool] = False

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
    constant_slope: ClassVar[bool] = True

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
        return self.limit * namespace(output).tanh(output / self.limit)

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
    constant_slope: ClassVar[bool] = True
    step: float = 0.1

    def __post_init__(self) -> None:
        if not self.step > 0:
            raise ValueError(f"quantized sensor: step={self.step!r} must be positive")

    def __call__(self, output):
        return self.step * namespace(output).round(output / self.step)

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
