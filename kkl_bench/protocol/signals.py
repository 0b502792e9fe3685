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
    """A protocol input regime: ``u(t) = signal(t; params(r))`` with ``r ~ U[0, 1)^3``."""

    name: ClassVar[str]
    param_names: ClassVar[tuple[str, ...]] = ()

    @abstractmethod
    def params_from_uniform(self, r: np.ndarray) -> np.ndarray:
        """Map ``r: (batch, 3)`` in [0, 1) to parameters ``(batch, len(param_names))``."""

    @abstractmethod
    def signal(self, t: np.ndarray, params: np.ndarray) -> np.ndarray:
        """Continuous-time signal. ``t: (steps,)`` in s, ``params: (batch, k)`` -> ``(batch, steps)``."""

    def sample(self, rng: np.random.Generator, n: int, t: np.ndarray) -> np.ndarray:
        """Draw ``n`` signals from this regime (an :class:`InputFamily`)."""
        return self.signal(t, self.params_from_uniform(rng.random((n, N_REGIME_NUMBERS))))

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
