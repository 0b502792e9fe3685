"""Encoder and decoder networks: MLPs with per-component normalization.

``NormalizedMLP`` computes ``out = mu_out + sigma_out * N((in - mu_in) / sigma_in)``
where ``N`` is a SiLU MLP. Its forward also accepts additive perturbations
of every layer's weights, one set per *window* (the dynamic HyperKKL's
input-dependent parameters), applied to a ``(windows, points, in)`` batch
with ``baddbmm``: weights are generated per window, never per sample.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator, Sequence

import torch
from torch import nn

LayerDeltas = Sequence[tuple[torch.Tensor, torch.Tensor]]
"""Per-layer ``(dW: (windows, out, in), db: (windows, out))`` perturbations."""


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Initialize networks inside this block from ``seed``, leaving the global RNG untouched."""
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        yield


class NormalizedMLP(nn.Module):
    """An MLP between normalized coordinates.

    Parameters
    ----------
    n_in, n_out: input and output sizes.
    hidden: width of each hidden layer.
    depth: number of hidden layers.
    """

    def __init__(self, n_in: int, n_out: int, hidden: int, depth: int) -> None:
        super().__init__()
        sizes = [n_in] + [hidden] * depth + [n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in itertools.pairwise(sizes))
        self.register_buffer("in_mean", torch.zeros(n_in))
        self.register_buffer("in_std", torch.ones(n_in))
        self.register_buffer("out_mean", torch.zeros(n_out))
        self.register_buffer("out_std", torch.ones(n_out))

    def set_normalization(self, inputs: torch.Tensor, outputs: torch.Tensor) -> None:
        """Fit the normalization to samples ``inputs: (n, n_in)`` and ``outputs: (n, n_out)``."""
        self.in_mean.copy_(inputs.mean(0))
        self.in_std.copy_(inputs.std(0).clamp_min(1e-6))
        self.out_mean.copy_(outputs.mean(0))
        self.out_std.copy_(outputs.std(0).clamp_min(1e-6))

    def normalized(self, x_tilde: torch.Tensor, deltas: LayerDeltas | None = None) -> torch.Tensor:
        """The bare network ``N`` on normalized inputs.

        ``x_tilde: (..., n_in)`` without deltas; ``(windows, points, n_in)`` with them.
        """
        h = x_tilde
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            if deltas is None:
                h = layer(h)
            else:
                d_weight, d_bias = deltas[i]
                weight = layer.weight + d_weight  # (windows, out, in)
                bias = layer.bias + d_bias  # (windows, out)
                h = torch.baddbmm(bias.unsqueeze(1), h, weight.transpose(1, 2))
            if i < last:
                h = nn.functional.silu(h)
        return h

    def forward(self, x: torch.Tensor, deltas: LayerDeltas | None = None) -> torch.Tensor:
        """``x: (..., n_in)`` in physical units -> ``(..., n_out)`` in physical units."""
        return self.out_mean + self.out_std * self.normalized(
            (x - self.in_mean) / self.in_std, deltas
        )

    def parameter_shapes(self) -> list[tuple[tuple[int, int], tuple[int]]]:
        """``[(weight shape, bias shape)]`` per layer, for hypernetwork heads."""
        return [(tuple(layer.weight.shape), tuple(layer.bias.shape)) for layer in self.layers]
