"""Injection KKL: the stationary KKL observer with the exact input injection (beyond the paper).

For a control-affine system ``dx/dt = f(x) + g u``, if ``T`` solves the
autonomous PDE then ``z = T(x)`` obeys ``dz/dt = A z + B y + dT/dx(x) g u``
(the paper's stationary approach; Bernard and Andrieu 2019). With learned
maps the injection is evaluated at the decoded estimate,
``phi_k = dT/dx(T*(z_k)) g u_k``: one forward-mode JVP of the encoder along
``g``, no extra training. The linear part is integrated exactly over each
sample (first-order hold of ``y``) and ``phi_k`` is held over the step
(exponential Euler), so zero input gives exactly ``autonomous_kkl``. It uses
the same cached Phase-1 model as the other KKL plugins.
"""

from __future__ import annotations

import numpy as np
import torch

from kkl_bench.kkl.autonomous import AutonomousModel, fit_phase1
from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.kkl.pde import directional_derivative
from kkl_bench.registry import estimators


def exact_injection(model: AutonomousModel, g: np.ndarray, u: np.ndarray):
    """``injection(k, z_k) = dT/dx(T*(z_k)) g u_k`` for :meth:`LatentObserver.run`.

    ``u: (batch, steps, 1)``; returns ``(batch, n_z)`` arrays (float64).
    """
    direction = torch.as_tensor(g, dtype=torch.float32)

    def injection(k: int, z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            x_hat = model.decoder(torch.as_tensor(z, dtype=torch.float32))
            _, along_g = directional_derivative(model.encoder, x_hat, direction.expand_as(x_hat))
        return u[:, k] * along_g.double().numpy()

    return injection


@estimators.register("injection_kkl")
class InjectionKKL(KKLEstimator):
    """``dz/dt = A z + B y + dT/dx(T*(z)) g u``, ``x_hat = T*(z)``, on the autonomous maps.

    Parameters
    ----------
    pde_weight: weight of the PDE residual in Phase 1 (shared with ``autonomous_kkl``).
    """

    name = "injection_kkl"

    def __init__(self, pde_weight: float = 1.0) -> None:
        self.pde_weight = pde_weight

    def fit(self, context):
        self.model_ = fit_phase1(context, self.pde_weight)
        return super().fit(context)

    def estimate(self, t, y, u):
        context = self.check_fitted()
        injection = exact_injection(self.model_, context.system.g, u)
        return self.model_.decode(self.model_.observer.run(y, injection))
