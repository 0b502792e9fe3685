"""Encoder and decoder networks: MLPs between whitened coordinates.

``NormalizedMLP`` computes ``out = mu_out + C_out N(W_in (in - mu_in))`` where
``N`` is a SiLU MLP, ``W_in`` whitens the inputs (ZCA: unit covariance) and
``C_out`` colours ``N``'s outputs, either per component (``sigma_out``) or
fully (the inverse whitening). Whitening matters: the latent states of a KKL
observer are filtered copies of the same output, so their covariance is
nearly singular, and per-component scaling leaves the network an input
whose informative directions are orders of magnitude smaller than the
others.

The forward also accepts additive perturbations of every layer's weights,
one set per *window* (the dynamic HyperKKL's input-dependent parameters),
applied to a ``(windows, points, in)`` batch with ``baddbmm``: weights are
generated per window, never per sample.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator, Sequence

import torch
from torch import nn

from kkl_bench.kkl.latent import is_diagonal

LayerDeltas = Sequence[tuple[torch.Tensor, torch.Tensor]]
"""Per-layer ``(dW: (windows, out, in), db: (windows, out))`` perturbations."""


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Initialize networks inside this block from ``seed``, on the CPU (the same initial
    weights wherever they are trained), leaving the global RNG untouched."""
    with torch.random.fork_rng(), torch.device("cpu"):
        torch.manual_seed(seed)
        yield


def affine_normalization(
    samples: torch.Tensor, whiten: bool, floor: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean ``(n,)``, whitening ``W`` and colouring ``C = W^-1`` ``(n, n)`` of ``samples: (m, n)``.

    ``(samples - mean) @ W`` has unit covariance (ZCA whitening, computed in
    float64; covariance eigenvalues are floored at ``floor`` times the
    largest, and at 1e-24) if ``whiten``, else unit variance per component. The floor keeps
    directions that carry only measurement noise (a linear system's latent states span
    ``n_x`` of their ``n_z`` dimensions) from being blown up to unit scale. Both matrices
    are symmetric.
    """
    samples = samples.double()
    mean = samples.mean(0)
    if whiten:
        variances, vectors = torch.linalg.eigh(torch.cov(samples.T).reshape(len(mean), -1))
        scales = variances.clamp_min(floor * variances.max()).clamp_min(1e-24).sqrt()
    else:
        vectors = torch.eye(len(mean), dtype=torch.float64)
        scales = samples.std(0).clamp_min(1e-6)
    whitening = vectors @ torch.diag(1.0 / scales) @ vectors.T
    coloring = vectors @ torch.diag(scales) @ vectors.T
    return mean.float(), whitening.float(), coloring.float()


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
        self.register_buffer("in_whitening", torch.eye(n_in))
        self.register_buffer("out_mean", torch.zeros(n_out))
        self.register_buffer("out_coloring", torch.eye(n_out))
        self.register_buffer("out_whitening", torch.eye(n_out))
        self._diagonal_output: bool | None = None  # see _output_scaled
        self.register_load_state_dict_post_hook(lambda module, _: module._forget_output_form())

    def _forget_output_form(self) -> None:
        self._diagonal_output = None

    def set_normalization(
        self, inputs: torch.Tensor, outputs: torch.Tensor, whiten_outputs: bool = False
    ) -> None:
        """Fit the normalization to samples ``inputs: (n, n_in)`` and ``outputs: (n, n_out)``.

        Inputs are always whitened; outputs are whitened if ``whiten_outputs``,
        else scaled per component (so that output errors weigh each component
        by its own spread, as the benchmark's RMSE does).
        """
        mean, whitening, _ = affine_normalization(inputs, whiten=True)
        self.in_mean.copy_(mean)
        self.in_whitening.copy_(whitening)
        mean, whitening, coloring = affine_normalization(outputs, whiten=whiten_outputs)
        self.out_mean.copy_(mean)
        self.out_whitening.copy_(whitening)
        self.out_coloring.copy_(coloring)
        self._forget_output_form()

    def input_difference(self, v: torch.Tensor) -> torch.Tensor:
        """A difference (or tangent) of inputs ``(..., n_in)`` in normalized units."""
        return v @ self.in_whitening

    def output_difference(self, d: torch.Tensor) -> torch.Tensor:
        """A difference (or tangent) of outputs ``(..., n_out)`` in normalized units."""
        return self._output_scaled(d, self.out_whitening)

    def _output_scaled(self, d: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
        """``d @ matrix`` for the output whitening or colouring: elementwise when the outputs
        are scaled per component (the matrices are diagonal), with the same numbers at a
        fraction of the cost for wide outputs (1620 latent states at Lorenz-96 n = 40)."""
        if self._diagonal_output is None:
            self._diagonal_output = is_diagonal(self.out_coloring)
        return d * matrix.diagonal() if self._diagonal_output else d @ matrix

    def normalized_output(self, out: torch.Tensor) -> torch.Tensor:
        """Physical outputs ``(..., n_out)`` in the network's normalized coordinates."""
        return self.output_difference(out - self.out_mean)

    def normalized(self, x_tilde: torch.Tensor, deltas: LayerDeltas | None = None) -> torch.Tensor:
        """The bare network ``N`` on normalized inputs.

        ``x_tilde: (..., n_in)`` without deltas; ``(windows, points, n_in)`` with them.
        """
        return self._network(x_tilde, deltas, centered=False)

    def _network(self, h: torch.Tensor, deltas: LayerDeltas | None, centered: bool) -> torch.Tensor:
        """``N`` on normalized inputs ``h``, or on ``centered`` ones (``x - mu_in``) it whitens."""
        folded = self._folded_first_weight(deltas) if centered else None
        last = len(self.layers) - 1
        for i in range(len(self.layers)):
            if i == 0 and centered:
                h = self._first_affine(h, deltas, folded)
            else:
                h = self._affine(i, h, deltas)
            if i < last:
                h = nn.functional.silu(h)
        return h

    def _folded_first_weight(self, deltas: LayerDeltas | None) -> torch.Tensor | None:
        """``W_0 W_in`` where whitening through the first layer pays: more inputs than hidden
        units (a decoder from 410 or 1620 latent states) and no perturbations; else None.
        ``centered @ (W_0 W_in)^T`` (``W_in`` is symmetric) costs ``n_in`` times ``hidden``
        per sample instead of ``n_in^2`` and equals layer 0 on whitened inputs up to float
        rounding."""
        layer = self.layers[0]
        if deltas is None and layer.in_features > layer.out_features:
            return layer.weight @ self.in_whitening
        return None

    def _first_affine(
        self,
        centered: torch.Tensor,
        deltas: LayerDeltas | None,
        folded: torch.Tensor | None,
        bias: bool = True,
    ) -> torch.Tensor:
        """Layer 0 on the whitened inputs ``centered @ W_in``, through ``folded`` if given
        (:meth:`_folded_first_weight`)."""
        if folded is not None:
            return nn.functional.linear(centered, folded, self.layers[0].bias if bias else None)
        return self._affine(0, self.input_difference(centered), deltas, bias)

    def _affine(
        self, i: int, h: torch.Tensor, deltas: LayerDeltas | None, bias: bool = True
    ) -> torch.Tensor:
        """Layer ``i``'s ``W h + b`` (``W h`` without ``bias``), perturbed by ``deltas``."""
        layer = self.layers[i]
        if deltas is None:
            return nn.functional.linear(h, layer.weight, layer.bias if bias else None)
        d_weight, d_bias = deltas[i]
        weight = (layer.weight + d_weight).transpose(1, 2)  # (windows, in, out)
        if not bias:
            return torch.bmm(h, weight)
        return torch.baddbmm((layer.bias + d_bias).unsqueeze(1), h, weight)

    def forward(self, x: torch.Tensor, deltas: LayerDeltas | None = None) -> torch.Tensor:
        """``x: (..., n_in)`` in physical units -> ``(..., n_out)`` in physical units."""
        n = self._network(x - self.in_mean, deltas, centered=True)
        return self.out_mean + self._output_scaled(n, self.out_coloring)

    def forward_with_tangent(
        self, x: torch.Tensor, v: torch.Tensor, deltas: LayerDeltas | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(N(x), dN/dx(x) v)`` in physical units, ``x, v: (..., n_in)``.

        Forward-mode differentiation written out: each layer carries its
        tangent through ``W`` and the SiLU's derivative, two matrix products
        per layer in one pass (``torch.func.jvp`` gives the same up to float
        rounding at many times the cost on small batches). Parameter gradients
        flow through both outputs.
        """
        h, dh = x - self.in_mean, v
        folded = self._folded_first_weight(deltas)
        last = len(self.layers) - 1
        for i in range(len(self.layers)):
            if i == 0:
                h = self._first_affine(h, deltas, folded)
                dh = self._first_affine(dh, deltas, folded, bias=False)
            else:
                h, dh = self._affine(i, h, deltas), self._affine(i, dh, deltas, bias=False)
            if i < last:
                sigmoid = torch.sigmoid(h)
                dh = dh * (sigmoid * (1 + h * (1 - sigmoid)))
                h = nn.functional.silu(h)
        return (
            self.out_mean + self._output_scaled(h, self.out_coloring),
            self._output_scaled(dh, self.out_coloring),
        )

    def parameter_shapes(self) -> list[tuple[tuple[int, int], tuple[int]]]:
        """``[(weight shape, bias shape)]`` per layer, for hypernetwork heads."""
        return [(tuple(layer.weight.shape), tuple(layer.bias.shape)) for layer in self.layers]
