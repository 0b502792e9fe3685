"""Training input families (each an :class:`~kkl_bench.protocol.signals.InputFamily`).

They span the protocol's test regimes without being them: the KKL plugins'
forced training data and the curriculum's levels are drawn from these, on
training streams only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ConstantFamily:
    """``u = c``, ``c ~ U[-level, level]``."""

    level: float = 1.0

    def sample(self, rng, n, t):
        return np.repeat(rng.uniform(-self.level, self.level, (n, 1)), len(t), axis=1)


@dataclass(frozen=True)
class SineFamily:
    """``u = A sin(w t + phi)``, ``A ~ U[amplitude]``, ``w ~ U[omega]`` (rad/s)."""

    omega: tuple[float, float]
    amplitude: tuple[float, float] = (0.3, 1.0)

    def sample(self, rng, n, t):
        amplitude = rng.uniform(*self.amplitude, (n, 1))
        omega = rng.uniform(*self.omega, (n, 1))
        phase = rng.uniform(0, 2 * np.pi, (n, 1))
        return amplitude * np.sin(omega * t + phase)


@dataclass(frozen=True)
class SquareFamily:
    """``u = A sign(sin(2 pi t / P + phi))``, ``P ~ U[period]`` (s)."""

    period: tuple[float, float]
    amplitude: tuple[float, float] = (0.3, 1.0)

    def sample(self, rng, n, t):
        amplitude = rng.uniform(*self.amplitude, (n, 1))
        period = rng.uniform(*self.period, (n, 1))
        phase = rng.uniform(0, 2 * np.pi, (n, 1))
        return amplitude * np.sign(np.sin(2 * np.pi * t / period + phase))


@dataclass(frozen=True)
class MultiSineFamily:
    """A sum of 2 to ``max_components`` sinusoids with ``w ~ U[omega]``, scaled to peak ``<= 1``."""

    omega: tuple[float, float] = (0.2, 2.5)
    max_components: int = 4

    def sample(self, rng, n, t):
        u = np.zeros((n, len(t)))
        counts = rng.integers(2, self.max_components + 1, n)
        for component in range(self.max_components):
            active = (component < counts)[:, None]
            omega = rng.uniform(*self.omega, (n, 1))
            phase = rng.uniform(0, 2 * np.pi, (n, 1))
            u += active * rng.uniform(0.2, 1.0, (n, 1)) * np.sin(omega * t + phase)
        return u / np.maximum(np.abs(u).max(axis=1, keepdims=True), 1.0)


@dataclass(frozen=True)
class MixtureFamily:
    """Each trajectory's signal from one of ``families``, chosen uniformly."""

    families: tuple

    def sample(self, rng, n, t):
        choice = rng.integers(len(self.families), size=n)
        u = np.empty((n, len(t)))
        for i, family in enumerate(self.families):
            rows = np.flatnonzero(choice == i)
            if len(rows):
                u[rows] = family.sample(rng, len(rows), t)
        return u


FORCED_TRAINING = MixtureFamily(
    (
        ConstantFamily(1.0),
        SineFamily((0.2, 2.5)),
        SquareFamily((1.5, 12.0)),
        MultiSineFamily(),
    )
)
"""The default forced-training family: constants, sines, squares and mixtures."""
