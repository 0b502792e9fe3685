"""Input regimes (protocol section 3): the paper's four and the ``ood-inputs`` families.

Each regime is a frozen dataclass whose fields are the ranges its parameters
are drawn from. The paper's regimes default to the paper's ranges; a track
file (``tasks/tracks/*.toml``) may set other ranges, and the families that
only tracks use have no defaults. Ranges are ``(low, high)`` pairs; a
parameter drawn "from" a range is ``low + (high - low) r`` for one of the
trajectory's uniform numbers ``r``.
"""

import math
from dataclasses import dataclass

import numpy as np

from kkl_bench.protocol.signals import Regime, check_range, uniform
from kkl_bench.registry import regimes


class RangeFields:
    """Validates every field as a ``(low, high)`` range (non-negative unless in ``signed``)."""

    signed: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            bounds = check_range(name, value, nonnegative=name not in self.signed)
            object.__setattr__(self, name, bounds)


def _phase(r: np.ndarray) -> np.ndarray:
    return 2.0 * np.pi * r


@regimes.register("zero")
@dataclass(frozen=True)
class Zero(Regime):
    """``u(t) = 0``."""

    name = "zero"

    def params_from_uniform(self, r):
        return np.empty((len(r), 0))

    def signal(self, t, params):
        return np.zeros((len(params), len(t)))


@regimes.register("constant")
@dataclass(frozen=True)
class Constant(RangeFields, Regime):
    """``u(t) = c`` with ``c ~ U[value]`` (paper: ``U[-1, 1]``)."""

    value: tuple[float, float] = (-1.0, 1.0)

    name = "constant"
    param_names = ("c",)
    signed = ("value",)

    def params_from_uniform(self, r):
        return uniform(r[:, :1], self.value)

    def signal(self, t, params):
        return np.broadcast_to(params[:, :1], (len(params), len(t))).copy()


@regimes.register("sinusoid")
@dataclass(frozen=True)
class Sinusoid(RangeFields, Regime):
    """``u(t) = A sin(w t + phi)``, ``A ~ U[amplitude]``, ``w ~ U[omega]`` rad/s,
    ``phi ~ U[0, 2 pi)`` (paper: ``A ~ U[0.5, 1]``, ``w ~ U[0.5, 2]``)."""

    amplitude: tuple[float, float] = (0.5, 1.0)
    omega: tuple[float, float] = (0.5, 2.0)

    name = "sinusoid"
    param_names = ("A", "w", "phi")

    def params_from_uniform(self, r):
        return np.stack(
            [uniform(r[:, 0], self.amplitude), uniform(r[:, 1], self.omega), _phase(r[:, 2])],
            axis=1,
        )

    def signal(self, t, params):
        amplitude, omega, phase = (params[:, i : i + 1] for i in range(3))
        return amplitude * np.sin(omega * t + phase)


@regimes.register("square")
@dataclass(frozen=True)
class Square(RangeFields, Regime):
    """``u(t) = A sign(sin(2 pi t / P + phi))``, ``A ~ U[amplitude]``, ``P ~ U[period]`` s,
    ``phi ~ U[0, 2 pi)`` (paper: ``A ~ U[0.5, 1]``, ``P ~ U[2, 10]``)."""

    amplitude: tuple[float, float] = (0.5, 1.0)
    period: tuple[float, float] = (2.0, 10.0)

    name = "square"
    param_names = ("A", "P", "phi")

    def params_from_uniform(self, r):
        return np.stack(
            [uniform(r[:, 0], self.amplitude), uniform(r[:, 1], self.period), _phase(r[:, 2])],
            axis=1,
        )

    def signal(self, t, params):
        amplitude, period, phase = (params[:, i : i + 1] for i in range(3))
        return amplitude * np.sign(np.sin(2.0 * np.pi * t / period + phase))


@regimes.register("chirp")
@dataclass(frozen=True)
class Chirp(RangeFields, Regime):
    """A linear chirp ``u(t) = A sin(w0 t + (w1 - w0) t^2 / (2 T) + phi)`` over the horizon
    ``T``: its frequency sweeps from ``omega[0]`` to ``omega[1]`` rad/s;
    ``A ~ U[amplitude]``, ``phi ~ U[0, 2 pi)``."""

    omega: tuple[float, float]
    amplitude: tuple[float, float]

    name = "chirp"
    param_names = ("A", "phi")

    def params_from_uniform(self, r):
        return np.stack([uniform(r[:, 0], self.amplitude), _phase(r[:, 1])], axis=1)

    def signal(self, t, params):
        amplitude, phase = params[:, :1], params[:, 1:2]
        start, end = self.omega
        sweep = (end - start) / (2.0 * max(t[-1], np.finfo(float).tiny))
        return amplitude * np.sin(start * t + sweep * t**2 + phase)


@regimes.register("multisine")
@dataclass(frozen=True)
class Multisine(RangeFields, Regime):
    """``u(t) = (A / k) sum_i sin(w_i t + phi_i)`` over ``k`` tones, ``k`` uniform on the
    integers of ``tones``, each ``w_i ~ U[omega]`` rad/s, ``phi_i ~ U[0, 2 pi)``,
    ``A ~ U[amplitude]`` (so ``|u| <= A``)."""

    tones: tuple[float, float]
    omega: tuple[float, float]
    amplitude: tuple[float, float]

    name = "multisine"

    def __post_init__(self) -> None:
        super().__post_init__()
        low, high = self.tones
        if low < 1 or low != int(low) or high != int(high):
            raise ValueError(f"tones must be whole numbers of at least 1, got {list(self.tones)}")

    @property
    def _max_tones(self) -> int:
        return int(self.tones[1])

    def n_numbers(self, t):
        return 2 + 2 * self._max_tones

    def params_from_uniform(self, r):
        low, high = int(self.tones[0]), self._max_tones
        count = np.minimum(low + np.floor(r[:, 0] * (high - low + 1)), high)
        amplitude = uniform(r[:, 1], self.amplitude)
        omegas = uniform(r[:, 2 : 2 + high], self.omega)
        phases = _phase(r[:, 2 + high :])
        return np.concatenate([count[:, None], amplitude[:, None], omegas, phases], axis=1)

    def signal(self, t, params):
        high = self._max_tones
        count, amplitude = params[:, :1], params[:, 1:2]
        omegas, phases = params[:, 2 : 2 + high, None], params[:, 2 + high :, None]
        used = (np.arange(high) < count)[..., None]  # (batch, tones, 1)
        tones = np.where(used, np.sin(omegas * t + phases), 0.0).sum(axis=1)
        return amplitude * tones / count


@regimes.register("random_steps")
@dataclass(frozen=True)
class RandomSteps(RangeFields, Regime):
    """A piecewise-constant signal: levels ``~ U[level]`` held for ``~ U[hold]`` s each,
    the first from ``t = 0``."""

    level: tuple[float, float]
    hold: tuple[float, float]

    name = "random_steps"
    signed = ("level",)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.hold[0] <= 0:
            raise ValueError(f"hold must be positive, got {list(self.hold)}")

    def _segments(self, t: np.ndarray) -> int:
        """Holds enough to cover the grid even if every one is as short as possible."""
        return math.ceil((t[-1] - t[0]) / self.hold[0]) + 1

    def n_numbers(self, t):
        return 2 * self._segments(t)

    def params_from_uniform(self, r):
        segments = r.shape[1] // 2
        return np.concatenate(
            [uniform(r[:, :segments], self.level), uniform(r[:, segments:], self.hold)], axis=1
        )

    def signal(self, t, params):
        segments = params.shape[1] // 2
        levels, holds = params[:, :segments], params[:, segments:]
        switches = np.cumsum(holds, axis=1)
        index = np.stack([np.searchsorted(s, t - t[0], side="right") for s in switches])
        return np.take_along_axis(levels, np.minimum(index, segments - 1), axis=1)


@regimes.register("ramp")
@dataclass(frozen=True)
class Ramp(RangeFields, Regime):
    """``u(t) = u0 + s t``, ``u0 ~ U[start]``, ``|s| ~ U[slope]`` (1/s), the sign of ``s``
    positive or negative with probability 1/2."""

    start: tuple[float, float]
    slope: tuple[float, float]

    name = "ramp"
    param_names = ("u0", "s")
    signed = ("start",)

    def params_from_uniform(self, r):
        sign = np.where(r[:, 2] < 0.5, -1.0, 1.0)
        return np.stack([uniform(r[:, 0], self.start), sign * uniform(r[:, 1], self.slope)], axis=1)

    def signal(self, t, params):
        return params[:, :1] + params[:, 1:2] * t
