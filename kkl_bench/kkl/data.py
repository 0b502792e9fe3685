"""Training data for KKL maps, produced by the observer the estimator will run.

Trajectories come from the protocol's simulator through the fit context's
training-data generator (noise included, training streams only). Their
outputs drive the exact latent observer from ``z0 = -A^{-1} B y0``, as at
test time, so the pairs ``(x_k, z_k)`` are what a decoder will see:

* after a burn-in of ``10 / lambda_min`` seconds, ``z_k`` has forgotten its
  initial value and approximates ``T(x_k)``: encoder targets;
* from the first scored sample on, ``(z_k, x_k)`` is exactly the decoder's
  test-time input and target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.latent import LatentObserver
from kkl_bench.measurement import held
from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.protocol.signals import InputFamily


@dataclass(frozen=True)
class ObserverData:
    """Simulated trajectories with the observer's latent state.

    Attributes
    ----------
    x: ``(n, steps, n_x)`` true states.
    z: ``(n, steps, n_z)`` latent observer states driven by ``y``.
    y: ``(n, steps, n_y)`` measurements.
    u: ``(n, steps, 1)`` inputs.
    """

    x: np.ndarray
    z: np.ndarray
    y: np.ndarray
    u: np.ndarray

    def settled(self, burn_in_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Flattened ``(x, z)`` pairs from sample ``burn_in_steps`` on."""
        x = self.x[:, burn_in_steps:].reshape(-1, self.x.shape[-1])
        z = self.z[:, burn_in_steps:].reshape(-1, self.z.shape[-1])
        return x, z

    def scored(self) -> tuple[np.ndarray, np.ndarray]:
        """Flattened ``(x, z)`` pairs on the protocol's scored window."""
        return self.settled(steady_state_start(self.x.shape[1]))


Box = tuple[np.ndarray, np.ndarray]
"""Lower and upper corners ``(n_x,)`` of a box of initial states."""


def observer_data(
    context: FitContext,
    observer: LatentObserver,
    inputs: InputFamily,
    n: int,
    stream: str,
    boxes: list[Box] | None = None,
) -> ObserverData:
    """Simulate ``n`` trajectories driven by ``inputs`` and run ``observer`` on their outputs.

    Initial states are drawn from ``boxes`` (default: the protocol's x0 box),
    the trajectories shared out evenly, each box on its own sub-stream.
    """
    boxes = boxes or [(context.x0_low, context.x0_high)]
    counts = [len(part) for part in np.array_split(np.arange(n), len(boxes))]
    parts = [
        context.training.simulate(
            inputs, count, stream=f"{stream}/box{i}", x0_low=low, x0_high=high
        )
        for i, ((low, high), count) in enumerate(zip(boxes, counts, strict=True))
        if count
    ]
    x, y, u = (np.concatenate([getattr(part, name) for part in parts]) for name in ("x", "y", "u"))
    y = held(y)
    return ObserverData(x, observer.run(y), y, u)


def validation_count(training_count: int) -> int:
    """How many validation trajectories a training on ``training_count`` draws to record
    its validation curve (protocol section 6.5): a quarter, at least 4."""
    return max(4, training_count // 4)


def burn_in_steps(rates: np.ndarray, dt: float) -> int:
    """Samples until the slowest latent mode has decayed by ``e^-10``."""
    return int(np.ceil(10.0 / (min(rates) * dt)))
