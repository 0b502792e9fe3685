"""Exogenous input signals: the protocol's test regimes and training input families.

An *input family* is anything that draws a batch of input signals sampled on a
time grid (:class:`InputFamily`). A *regime* is the protocol's kind of family:
its parameters are a fixed function of three uniform numbers ``r`` drawn from
the trajectory's random stream, so test sets are reproducible bit for bit.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np

N_REGIME_NUMBERS = 3
"""How many uniform numbers every trajectory draws for its regime (used as needed)."""


@runtime_checkable
class InputFamily(Protocol):
    """A distribution over input signals, sampled on a time grid."""

    def sample(self, rng: np.random.Generator, n: int, t: np.ndarray) -> np.ndarray:
        """Draw ``n`` signals. ``t: (steps,)`` in s -> ``u: (n, steps)``."""
        ...


class Regime(ABC):
    """A protocol input regime: ``u(t) = signal(t; params(r))`` with ``r ~ U[0, 1)^m``.

    ``m`` is :meth:`n_numbers` (three for the paper's regimes). Concrete
    regimes are frozen dataclasses whose fields are the ranges the parameters
    are drawn from; their defaults are the paper's, and a track may set others.
    """

    name: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]] = ()

    def n_numbers(self, t: np.ndarray) -> int:
        """How many uniform numbers one trajectory on the grid ``t: (steps,)`` draws."""
        return N_REGIME_NUMBERS

    @abstractmethod
    def params_from_uniform(self, r: np.ndarray) -> np.ndarray:
        """Map ``r: (batch, m)`` in [0, 1) to parameters ``(batch, k)``."""

    @abstractmethod
    def signal(self, t: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Continuous-time signal. ``t: (steps,)`` in s, ``params: (batch, k)`` -> ``(batch, steps)``."""

    def sample(self, rng: np.random.Generator, n: int, t: np.ndarray) -> np.ndarray:
        """Draw ``n`` signals from this regime (an :class:`InputFamily`)."""
        return self.signal(t, self.params_from_uniform(rng.random((n, self.n_numbers(t)))))


def check_range(name: str, value: object, nonnegative: bool = False) -> tuple[float, float]:
    """``value`` as a ``(low, high)`` pair of numbers with ``low <= high``.

    Raises ``ValueError`` naming the parameter and what is wrong with it.
    """
    if (
        not isinstance(value, list | tuple)
        or len(value) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise ValueError(f"{name} must be a [low, high] pair of numbers, got {value!r}")
    low, high = float(value[0]), float(value[1])
    if not (np.isfinite(low) and np.isfinite(high)) or low > high:
        raise ValueError(f"{name} must be finite with low <= high, got {list(value)}")
    if nonnegative and low < 0:
        raise ValueError(f"{name} must not be negative, got {list(value)}")
    return low, high


def uniform(r: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    """``r`` in [0, 1) mapped onto ``bounds = (low, high)``: ``low + (high - low) r``."""
    low, high = bounds
    return low + (high - low) * r
