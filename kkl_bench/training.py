"""The training-data generator estimators receive in ``fit``, and the training input
families the built-in learned rows draw from.

It simulates the system exactly as the protocol does (RK4, zero-order-hold
input, process and measurement noise) with any input family, any number of
trajectories and the estimator's own seed, on streams that can never coincide
with a test stream. The families (each an
:class:`~kkl_bench.protocol.signals.InputFamily`) span the protocol's test regimes
without being them: the forced training data of the KKL plugins and of the sequence
networks, the curriculum's levels and the filters' validation data are drawn from them.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from kkl_bench.measurement import MeasurementModel, NoiseLaw
from kkl_bench.protocol import PROTOCOL_VERSION
from kkl_bench.protocol.signals import InputFamily
from kkl_bench.protocol.simulate import Trajectories, simulate
from kkl_bench.protocol.system import System


class TrainingData:
    """Simulates training trajectories of one system.

    Parameters
    ----------
    system: the model, its output read by the task's sensor (``FitContext.system``).
    dt: sampling step (s).
    n_samples: default samples per trajectory.
    sigma_w, sigma_v: the process noise's and the measurement noise's standard deviations.
    seed: the run's seed; every stream below is derived from it.
    measurement: the sampling and the noise law of the measurements (its sensor is
        already in ``system``); default: Gaussian noise of ``sigma_v`` at every sample.
    """

    def __init__(
        self,
        system: System,
        dt: float,
        n_samples: int,
        sigma_w: float,
        sigma_v: float,
        seed: int,
        measurement: MeasurementModel | None = None,
    ) -> None:
        self.system = system
        self.dt = dt
        self.n_samples = n_samples
        self.sigma_w = sigma_w
        self.sigma_v = sigma_v
        self.seed = seed
        self.measurement = measurement or MeasurementModel(noise=NoiseLaw(sigma=sigma_v))

    def with_system(self, system: System) -> TrainingData:
        """The same generator (streams, noise, measurement model) simulating ``system``
        (e.g. the model calibrated on logged data); streams are keyed by the system's name,
        so a system of the same name draws the same inputs, initial states and noise."""
        return TrainingData(
            system,
            self.dt,
            self.n_samples,
            self.sigma_w,
            self.sigma_v,
            self.seed,
            self.measurement,
        )

    def rng(self, stream: str) -> np.random.Generator:
        """A generator for the named stream, e.g. ``"train"`` or ``"validation"``.

        Streams are keyed by system, name and run seed; the protocol's test
        streams ("test") are refused.
        """
        if stream == "test" or stream.endswith("/test"):
            raise ValueError(f"stream {stream!r} is reserved for the test sets")
        label = f"kkl-bench/v{PROTOCOL_VERSION}/{self.system.name}/{stream}/train-data"
        return np.random.default_rng(
            np.random.SeedSequence([zlib.crc32(label.encode()), self.seed])
        )

    def simulate(
        self,
        inputs: InputFamily,
        n: int,
        stream: str = "train",
        n_samples: int | None = None,
        x0_low: np.ndarray | None = None,
        x0_high: np.ndarray | None = None,
        noise: bool = True,
    ) -> Trajectories:
        """Simulate ``n`` trajectories driven by signals drawn from ``inputs``.

        Parameters
        ----------
        inputs: any :class:`~kkl_bench.protocol.signals.InputFamily`, e.g. a registered regime.
        n: number of trajectories.
        stream: name of the random stream (not ``"test"``).
        n_samples: samples per trajectory (default: the protocol's).
        x0_low, x0_high: ``(n_x,)`` box for initial states (default: the system's x0 box).
        noise: add the process and measurement noise (and leave out the samples the
            measurement model does not observe: NaN).

        Returns
        -------
        Trajectories with ``x: (n, n_samples, n_x)``, ``y: (n, n_samples, n_y)``,
        ``u: (n, n_samples, 1)``.
        """
        if n < 1:
            raise ValueError(f"n must be a positive number of trajectories, got {n}")
        steps = self.n_samples if n_samples is None else n_samples
        rng = self.rng(stream)
        low = self.system.x0_low if x0_low is None else np.asarray(x0_low, dtype=float)
        high = self.system.x0_high if x0_high is None else np.asarray(x0_high, dtype=float)
        x0 = rng.uniform(low, high, (n, self.system.n_x))
        u = inputs.sample(rng, n, self.dt * np.arange(steps))
        if not noise:
            return simulate(self.system, x0, u, self.dt)
        process_noise = self.sigma_w * rng.standard_normal((n, steps - 1, self.system.n_x))
        measurement_noise = self.measurement.noise.sample(rng, (n, steps, self.system.n_y))
        data = simulate(self.system, x0, u, self.dt, process_noise)
        return Trajectories(
            data.t, data.u, data.x, self.measurement.measure(data.y, measurement_noise)
        )


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
