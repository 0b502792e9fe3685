"""The KKL PDE residual ``dT/dx(x) v - A T(x) - B h(x)``, by one Jacobian-vector product.

``v`` is the vector field: ``f(x)`` for the autonomous PDE, ``f(x) + g u``
for the forced one. The directional derivative ``dT/dx(x) v`` is one
forward pass carrying a tangent through the encoder
(:meth:`NormalizedMLP.forward_with_tangent`), never a full per-sample
Jacobian; parameter gradients flow through it.
"""

from __future__ import annotations

import torch

from kkl_bench.kkl.latent import latent_drift
from kkl_bench.kkl.networks import LayerDeltas, NormalizedMLP


def directional_derivative(
    encoder: NormalizedMLP, x: torch.Tensor, v: torch.Tensor, deltas: LayerDeltas | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(T(x), dT/dx(x) v)`` for ``x, v: (..., n_x)`` (``deltas``: a hypernetwork's
    weight perturbations, see :meth:`NormalizedMLP.normalized`). Another module
    (an exact map in a test) goes through ``torch.func.jvp``."""
    if isinstance(encoder, NormalizedMLP):
        return encoder.forward_with_tangent(x, v, deltas)
    return torch.func.jvp(encoder, (x,), (v,))


def pde_residual(
    encoder: NormalizedMLP,
    x: torch.Tensor,
    v: torch.Tensor,
    h_x: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
) -> torch.Tensor:
    """``dT/dx(x) v - A T(x) - B h(x)``: ``x, v: (..., n_x)``, ``h_x: (..., n_y)`` -> ``(..., n_z)``."""
    t_x, dt_v = directional_derivative(encoder, x, v)
    return dt_v - latent_drift(t_x, a) - h_x @ b.T


def normalized_field_rms(encoder: NormalizedMLP, vector_field: torch.Tensor) -> torch.Tensor:
    """RMS norm of ``vector_field: (n, n_x)`` in the encoder's normalized input units.

    Dividing a residual in normalized latent units by it makes the PDE term
    comparable to the data term whatever the system's speed.
    """
    return encoder.input_difference(vector_field).pow(2).sum(-1).mean().sqrt().clamp_min(1e-6)
