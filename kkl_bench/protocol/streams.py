"""The protocol's pinned random streams (protocol section 4).

Test trajectory ``i`` of a task draws, from its own generator and in this
order: ``x0``, the regime's uniform numbers ``r`` (three for the paper's
regimes), the process noise and the measurement noise. Any implementation
following these rules draws the same numbers.
"""

from __future__ import annotations

import contextlib
import contextvars
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from kkl_bench.protocol import PROTOCOL_VERSION
from kkl_bench.protocol.signals import N_REGIME_NUMBERS

_test_streams_sealed = contextvars.ContextVar("test_streams_sealed", default=False)


class TestStreamAccessError(RuntimeError):
    """Code that must not see the test sets asked for a test stream."""

    __test__ = False  # not a pytest class


@contextlib.contextmanager
def sealed_test_streams() -> Iterator[None]:
    """Within this block, asking for a test stream (or a true plant's parameter errors)
    raises :class:`TestStreamAccessError`.

    The conformance kit fits and runs estimators inside it, so an estimator
    that peeks at the test sets fails its checks.
    """
    token = _test_streams_sealed.set(True)
    try:
        yield
    finally:
        _test_streams_sealed.reset(token)


SEALED_SPLITS = ("test", "plant")
"""Streams no estimator may ask for: the test trajectories and the true plants of the
``mismatch`` track (its parameter errors)."""

PAPER_TRACK = "paper"
"""The track of the paper's 16 cells, whose stream keys carry no track name."""


def root_seed(system: str, regime: str, split: str, track: str = PAPER_TRACK) -> int:
    """``zlib.crc32(b"kkl-bench/v1/<system>/<regime>/<split>")`` for the paper track,
    ``zlib.crc32(b"kkl-bench/v1/<track>/<system>/<regime>/<split>")`` for any other."""
    if split in SEALED_SPLITS and _test_streams_sealed.get():
        raise TestStreamAccessError(
            f"the {split} stream of {track}/{system}/{regime} was requested where test data "
            "and true plants are off-limits"
        )
    prefix = "" if track == PAPER_TRACK else f"{track}/"
    return zlib.crc32(f"kkl-bench/v{PROTOCOL_VERSION}/{prefix}{system}/{regime}/{split}".encode())


def trajectory_rng(root: int, index: int) -> np.random.Generator:
    """The generator of trajectory ``index`` (0-based) under ``root``."""
    return np.random.default_rng(np.random.SeedSequence(root, spawn_key=(index,)))


@dataclass(frozen=True)
class TrajectoryDraws:
    """Everything random about one trajectory.

    Attributes
    ----------
    x0: ``(n_x,)`` initial state.
    r: ``(n_numbers,)`` uniform numbers the regime maps to its parameters.
    process_noise: ``(steps - 1, n_x)`` samples ``w_k``.
    measurement_noise: ``(steps, n_y)`` samples ``v_k``.
    """

    x0: np.ndarray
    r: np.ndarray
    process_noise: np.ndarray
    measurement_noise: np.ndarray


def draw_trajectory(
    rng: np.random.Generator,
    x0_low: np.ndarray,
    x0_high: np.ndarray,
    steps: int,
    sigma_w: float,
    sigma_v: float,
    n_numbers: int = N_REGIME_NUMBERS,
    n_y: int = 1,
    noise_law: Callable[[np.random.Generator, tuple[int, ...]], np.ndarray] | None = None,
) -> TrajectoryDraws:
    """Draw one trajectory's randomness in the protocol's order (with one output, the
    measurement noise is the same numbers as protocol v1's ``(steps,)`` draw).

    ``noise_law(rng, shape)`` draws the measurement noise when the task declares a law
    other than the Gaussian (:meth:`kkl_bench.measurement.NoiseLaw.sample`); by default
    it is ``sigma_v`` times standard normal numbers."""
    x0 = rng.uniform(x0_low, x0_high, len(x0_low))
    r = rng.random(n_numbers)
    process_noise = sigma_w * rng.standard_normal((steps - 1, len(x0_low)))
    if noise_law is None:
        measurement_noise = sigma_v * rng.standard_normal((steps, n_y))
    else:
        measurement_noise = noise_law(rng, (steps, n_y))
    return TrajectoryDraws(x0, r, process_noise, measurement_noise)
