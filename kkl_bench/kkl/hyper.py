"""Hypernetwork heads: from an input-window context to per-layer weight perturbations.

Both heads return, for contexts ``c: (n, d)``, the perturbations
``[(dW: (n, out, in), db: (n, out))]`` of a :class:`NormalizedMLP`, as
``G(c) - G(c0)`` where ``c0`` is the context of the all-zero window, so the
perturbation vanishes as the input does; callers use the base network
itself where a window is exactly zero.

* :class:`ChunkedHead` (the paper's method section): the flattened parameter
  vector is cut into chunks of ``chunk`` entries; one MLP maps the context
  and a learned embedding of the chunk index to that chunk. Full rank.
* :class:`LowRankHead` (the paper's implementation details): ``dW = U V^T``
  with ``U: (out, r)``, ``V: (in, r)`` produced by linear maps of the context.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from kkl_bench.kkl.networks import LayerDeltas


def _split(flat: torch.Tensor, shapes) -> LayerDeltas:
    """``flat: (n, P)`` -> per-layer ``(dW, db)`` with the given shapes."""
    deltas, offset = [], 0
    for weight_shape, bias_shape in shapes:
        size = math.prod(weight_shape)
        weight = flat[:, offset : offset + size].reshape(-1, *weight_shape)
        offset += size
        bias = flat[:, offset : offset + bias_shape[0]]
        offset += bias_shape[0]
        deltas.append((weight, bias))
    return deltas


class ChunkedHead(nn.Module):
    """Chunked full-rank generation of every parameter of a target network."""

    def __init__(
        self, shapes, context: int, chunk: int = 1024, embedding: int = 8, hidden: int = 64
    ) -> None:
        super().__init__()
        self.shapes = shapes
        self.n_params = sum(math.prod(w) + b[0] for w, b in shapes)
        self.n_chunks = math.ceil(self.n_params / chunk)
        self.embeddings = nn.Parameter(0.1 * torch.randn(self.n_chunks, embedding))
        self.body = nn.Sequential(
            nn.Linear(context + embedding, hidden), nn.SiLU(), nn.Linear(hidden, chunk)
        )
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)

    def _generate(self, c: torch.Tensor) -> torch.Tensor:
        n = c.shape[0]
        inputs = torch.cat(
            [c.unsqueeze(1).expand(n, self.n_chunks, -1), self.embeddings.expand(n, -1, -1)], dim=-1
        )
        return self.body(inputs).reshape(n, -1)[:, : self.n_params]

    def forward(self, c: torch.Tensor, c0: torch.Tensor) -> LayerDeltas:
        return _split(self._generate(c) - self._generate(c0), self.shapes)


class LowRankHead(nn.Module):
    """Rank-``rank`` weight perturbations ``U V^T`` and bias perturbations per layer."""

    def __init__(self, shapes, context: int, rank: int = 8) -> None:
        super().__init__()
        self.shapes = shapes
        self.rank = rank
        sizes = [(w[0] + w[1]) * rank + b[0] for w, b in shapes]
        self.heads = nn.ModuleList(nn.Linear(context, size) for size in sizes)
        for head in self.heads:
            nn.init.zeros_(head.bias)
            nn.init.normal_(head.weight, std=1e-3)

    def _generate(self, c: torch.Tensor) -> LayerDeltas:
        deltas = []
        for head, (weight_shape, _) in zip(self.heads, self.shapes, strict=True):
            out_size, in_size = weight_shape
            flat = head(c)
            left = flat[:, : out_size * self.rank].reshape(-1, out_size, self.rank)
            right = flat[:, out_size * self.rank : (out_size + in_size) * self.rank].reshape(
                -1, in_size, self.rank
            )
            deltas.append(
                (left @ right.transpose(1, 2), flat[:, (out_size + in_size) * self.rank :])
            )
        return deltas

    def forward(self, c: torch.Tensor, c0: torch.Tensor) -> LayerDeltas:
        generated, baseline = self._generate(c), self._generate(c0)
        return [(w - w0, b - b0) for (w, b), (w0, b0) in zip(generated, baseline, strict=True)]


def make_head(kind: str, shapes, context: int, chunk: int, rank: int) -> nn.Module:
    """``"chunked"`` or ``"lowrank"``; the error lists the valid kinds."""
    if kind == "chunked":
        return ChunkedHead(shapes, context, chunk=chunk)
    if kind == "lowrank":
        return LowRankHead(shapes, context, rank=rank)
    raise ValueError(f"unknown hypernetwork head {kind!r}; valid heads: chunked, lowrank")
