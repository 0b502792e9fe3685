"""Choosing the gain of a latent injection on validation data (the notes' "Lorenz guard").

An injection ``phi(z, u)`` built from learned maps is only as good as the
encoder's Jacobian along ``g``; where that is poor (Van der Pol off its limit
cycle, Lorenz) the full injection does more harm than ignoring the input.
:func:`select_gain` scales it by the gain with the lowest RMSE on forced
validation trajectories of a training stream; gain 0 is the input-ignoring
observer, gain 1 the full injection.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.autonomous import AutonomousModel
from kkl_bench.protocol.metrics import steady_state_start
from kkl_bench.protocol.signals import InputFamily
from kkl_bench.training import FORCED_TRAINING

GAINS = (0.0, 0.25, 0.5, 0.75, 1.0)

Injection = Callable[[int, np.ndarray], np.ndarray]


def simulate_families(
    context: FitContext, families: Mapping[str, InputFamily], n: int, stream: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x, y, u`` of ``n`` training trajectories per input family (stream
    ``{stream}/{label}``), concatenated along the batch."""
    parts = [
        context.training.simulate(inputs, n, stream=f"{stream}/{label}")
        for label, inputs in families.items()
    ]
    return tuple(np.concatenate([getattr(part, name) for part in parts]) for name in "xyu")


def select_gain(
    context: FitContext,
    model: AutonomousModel,
    injection_for: Callable[[np.ndarray, float], Injection],
    n: int,
    stream: str,
    gains: tuple[float, ...] = GAINS,
) -> tuple[float, dict[str, float]]:
    """The gain with the lowest RMSE of ``model``'s observer over the scored window of
    ``n`` forced validation trajectories, and every gain's RMSE (``inf`` if the
    observer diverged with that gain).

    ``injection_for(u, gain)`` returns the injection for :meth:`LatentObserver.run`
    given ``u: (batch, steps, 1)``.
    """
    x, y, u = simulate_families(context, {"forced": FORCED_TRAINING}, n, stream)
    start = steady_state_start(x.shape[1])
    scores = {}
    for gain in gains:
        with np.errstate(over="ignore", invalid="ignore"):
            x_hat = model.decode(model.observer.run(y, injection_for(u, gain)))
            rmse = float(np.sqrt(np.mean((x_hat[:, start:] - x[:, start:]) ** 2)))
        scores[f"{gain:g}"] = rmse if np.isfinite(rmse) else float("inf")  # diverged
    return min(gains, key=lambda gain: scores[f"{gain:g}"]), scores
