"""Fitting a decoder ``T*`` to (latent state, state) pairs, and its RMSE on validation
pairs: what Phase 1, the curriculum's levels and ``injection_kkl``'s adaptation share."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from kkl_bench.kkl.networks import NormalizedMLP
from kkl_bench.kkl.optimize import Training, minimize
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.support.devices import draw_integers, to_numpy


def train_decoder(
    decoder: NormalizedMLP,
    z: torch.Tensor,
    x: torch.Tensor,
    steps: int,
    batch: int,
    generator: torch.Generator,
    description: str,
    validation: tuple[torch.Tensor, np.ndarray] | None = None,
    rule: PlateauRule | None = None,
) -> Training:
    """Fit ``decoder`` to pairs ``z: (n, n_z) -> x: (n, n_x)`` in normalized state units;
    with ``validation = (z_val, x_val)`` (a tensor and an array), record its RMSE on them
    (state units) as it goes and, with a ``rule``, end by the plateau rule at most
    ``steps`` steps in; without, run ``steps`` steps."""

    def loss(_):
        rows = draw_integers(len(z), (batch,), generator)
        return decoder.output_difference(decoder(z[rows]) - x[rows]).pow(2).sum(-1).mean()

    error = None if validation is None else decoder_rmse(decoder, *validation)
    return minimize(
        loss,
        decoder.parameters(),
        steps,
        batch,
        description=description,
        validation=error,
        rule=rule,
    )


def decoder_rmse(decoder: NormalizedMLP, z: torch.Tensor, x: np.ndarray) -> Callable[[], float]:
    """The RMSE of ``decoder(z)`` against ``x`` (all samples and states, state units), as
    a function to call as training goes (``z: (n, n_z)`` tensor, ``x: (n, n_x)`` array)."""

    def error() -> float:
        with torch.no_grad():
            return float(np.sqrt(np.mean((to_numpy(decoder(z)) - x) ** 2)))

    return error
