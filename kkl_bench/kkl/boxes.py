"""Where Phase 1's unforced training trajectories start (:func:`training_boxes`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from kkl_bench.estimator import FitContext
from kkl_bench.kkl.data import Box
from kkl_bench.protocol.signals import InputFamily
from kkl_bench.registry import regimes
from kkl_bench.training import FORCED_TRAINING

if TYPE_CHECKING:
    from kkl_bench.kkl.autonomous import Phase1Config

TRAIN_BOXES = ("auto", "covering", "protocol")

COVERAGE_MARGIN = 0.1
"""``"auto"`` adds the covering box when forced training states exceed the range of
unforced ones by more than this fraction of that range in some state."""


def _state_range(context: FitContext, inputs: InputFamily, n: int, stream: str) -> Box:
    """Per-state minimum and maximum ``(n_x,)`` over ``n`` training trajectories."""
    x = context.training.simulate(inputs, n, stream=stream).x
    states = x.reshape(-1, x.shape[-1])
    return states.min(0), states.max(0)


def training_boxes(context: FitContext, config: Phase1Config) -> list[Box]:
    """Boxes the unforced Phase-1 trajectories start from (one sub-stream each).

    The covering box is the per-state range of forced training trajectories
    (:data:`~kkl_bench.training.FORCED_TRAINING` inputs, a training stream),
    joined with the x0 box: forced Duffing reaches ``|x1|`` of about 7, far
    outside ``[-1, 1]``, and maps trained on the x0 box alone are wrong
    there. Where unforced orbits already span the forced states (Van der
    Pol's limit cycle, the chaotic attractors), starting trajectories all
    over that range only dilutes the data, and ``"auto"`` keeps the x0 box.
    """
    if config.train_box not in TRAIN_BOXES:
        raise ValueError(f"unknown train_box {config.train_box!r}; valid: {', '.join(TRAIN_BOXES)}")
    protocol_box = (context.x0_low, context.x0_high)
    if config.train_box == "protocol":
        return [protocol_box]
    n = config.train_trajectories
    forced_low, forced_high = _state_range(context, FORCED_TRAINING, n, "kkl/box")
    if config.train_box == "auto":
        low, high = _state_range(context, regimes.get("zero")(), n, "kkl/box/unforced")
        margin = COVERAGE_MARGIN * (high - low)
        if np.all(forced_low >= low - margin) and np.all(forced_high <= high + margin):
            return [protocol_box]
    covering = (np.minimum(forced_low, context.x0_low), np.maximum(forced_high, context.x0_high))
    return [protocol_box, covering]
