"""Trained SiLU MLPs frozen into float32 numpy for the observers' per-sample loops.

A KKL observer evaluates its small networks once per sample on a batch of a
few trajectories. There, torch spends most of each call on dispatch rather
than arithmetic; a numpy copy with the input normalization folded into the
first layer and the output colouring into the last does the same arithmetic
with a few plain matrix products. Results equal the torch networks' up to
float32 rounding (tested).

The sigmoid is ``(1 + tanh(h / 2)) / 2``, computed in place: numpy's float32
``tanh`` is vectorized, and on a ``(20, 128)`` block it took 2.3 us against
8.8 us for ``scipy.special.expit`` (one thread, measured side by side), more
than the matrix product of a 128-wide layer (6.8 us).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from kkl_bench.kkl.networks import NormalizedMLP
from kkl_bench.support import flops


def _sigmoid(h: np.ndarray) -> np.ndarray:
    """``sigmoid(h)`` as a new float32 array."""
    s = np.multiply(h, np.float32(0.5))
    np.tanh(s, out=s)
    s *= np.float32(0.5)
    s += np.float32(0.5)
    return s


def _silu_in_place(h: np.ndarray) -> None:
    """``h <- silu(h) = h sigmoid(h)``."""
    h *= _sigmoid(h)


def _silu_with_tangent_in_place(h: np.ndarray, tangent: np.ndarray) -> None:
    """``h <- silu(h)`` and ``tangent <- silu'(h) tangent``, with
    ``silu'(h) = s + silu(h) (1 - s)`` for ``s = sigmoid(h)``."""
    s = _sigmoid(h)
    h *= s
    tangent_times_s = tangent * s
    np.subtract(np.float32(1.0), s, out=s)
    s *= h
    tangent *= s
    tangent += tangent_times_s


@dataclass(frozen=True)
class FrozenMLP:
    """``x -> h_L``, ``h_0 = x``, ``h_{i+1} = silu(h_i @ weights[i] + biases[i])`` (no SiLU last).

    ``weights[i]: (n_i, n_{i+1})`` and ``biases[i]: (n_{i+1},)``, float32.
    """

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]

    @classmethod
    def from_layers(cls, layers: list[nn.Linear]) -> FrozenMLP:
        """The MLP of consecutive ``nn.Linear`` layers with SiLU between them."""
        return cls(
            tuple(_array(layer.weight.T) for layer in layers),
            tuple(
                _array(layer.bias)
                if layer.bias is not None
                else np.zeros(layer.out_features, np.float32)
                for layer in layers
            ),
        )

    @classmethod
    def of(cls, network: NormalizedMLP | nn.Linear) -> FrozenMLP:
        """A frozen copy of a :class:`NormalizedMLP` or of a single ``nn.Linear`` layer."""
        if isinstance(network, NormalizedMLP):
            return cls.from_normalized(network)
        if isinstance(network, nn.Linear):
            return cls.from_layers([network])
        raise TypeError(
            f"cannot freeze a {type(network).__name__}; expected NormalizedMLP or Linear"
        )

    @classmethod
    def from_normalized(cls, network: NormalizedMLP) -> FrozenMLP:
        """``network``'s map between physical units, its normalization folded in."""
        return (
            cls.from_layers(list(network.layers))
            .after_affine(network.in_mean, network.in_whitening)
            .before_affine(network.out_coloring, network.out_mean)
        )

    def after_affine(self, mean: torch.Tensor, matrix: torch.Tensor) -> FrozenMLP:
        """The MLP of ``(x - mean) @ matrix`` (folded into the first layer, in float64)."""
        weight = _array(matrix, np.float64) @ self.weights[0]
        bias = self.biases[0] - _array(mean, np.float64) @ weight
        return self._replace(0, weight, bias)

    def before_affine(self, matrix: torch.Tensor, shift: torch.Tensor) -> FrozenMLP:
        """The MLP followed by ``h -> h @ matrix + shift`` (folded into the last layer)."""
        matrix = _array(matrix, np.float64)
        return self._replace(
            -1, self.weights[-1] @ matrix, self.biases[-1] @ matrix + _array(shift, np.float64)
        )

    def split_input(self, n: int) -> tuple[FrozenMLP, np.ndarray]:
        """This MLP on inputs ``[a, c]`` as an MLP of ``a: (batch, n)`` and ``c``'s first-layer weight.

        ``mlp([a, c]) == first(a, offset=c @ weight)`` for the returned ``(first, weight)``;
        a ``c`` known in advance (an input window's embedding) is multiplied
        once for all samples.
        """
        return self._replace(0, self.weights[0][:n], self.biases[0]), self.weights[0][n:]

    def _replace(self, i: int, weight: np.ndarray, bias: np.ndarray) -> FrozenMLP:
        weights, biases = list(self.weights), list(self.biases)
        weights[i] = np.ascontiguousarray(weight, dtype=np.float32)
        biases[i] = np.ascontiguousarray(bias, dtype=np.float32)
        return FrozenMLP(tuple(weights), tuple(biases))

    def __call__(self, x: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
        """``x: (batch, n_in)`` -> ``(batch, n_out)`` (float32); ``offset: (batch, n_1)`` is
        added to the first layer's pre-activation (see :meth:`split_input`)."""
        h = np.asarray(x, dtype=np.float32)
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            flops.add(flops.products(h.size // weight.shape[0], *weight.shape))
            h = h @ weight
            h += bias
            if i == 0 and offset is not None:
                h += offset
            if i < last:
                _silu_in_place(h)
        return h

    def with_tangent(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The output and its derivative along ``v``: ``x: (batch, n_in)``, ``v: (batch, n_in)``
        or one direction ``(n_in,)`` for all -> two ``(batch, n_out)`` (float32).

        After the first layer, value and tangent go through each layer's weight in one
        matrix product; a single direction's first-layer tangent is computed once.
        """
        batch = len(x)
        weight, bias = self.weights[0], self.biases[0]
        stacked = np.empty((2 * batch, weight.shape[1]), dtype=np.float32)
        value, tangent = stacked[:batch], stacked[batch:]
        np.matmul(np.asarray(x, dtype=np.float32), weight, out=value)
        value += bias
        tangent[:] = np.asarray(v, dtype=np.float32) @ weight
        directions = 1 if np.ndim(v) == 1 else batch
        flops.add(flops.products(batch + directions, *weight.shape))
        for weight, bias in zip(self.weights[1:], self.biases[1:], strict=True):
            flops.add(flops.products(2 * batch, *weight.shape))
            _silu_with_tangent_in_place(value, tangent)
            stacked = stacked @ weight
            value, tangent = stacked[:batch], stacked[batch:]
            value += bias
        return value, tangent


def _array(tensor: torch.Tensor, dtype=np.float32) -> np.ndarray:
    """A C-ordered copy (matrix products on transposed views are several times slower)."""
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=dtype)
