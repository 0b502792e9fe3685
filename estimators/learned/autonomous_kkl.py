"""Autonomous KKL observer (the paper's Phase 1): ignores the input at test time."""

from __future__ import annotations

from kkl_bench.kkl.autonomous import fit_phase1
from kkl_bench.kkl.estimator import KKLEstimator
from kkl_bench.registry import estimators


@estimators.register("autonomous_kkl")
class AutonomousKKL(KKLEstimator):
    """``z' = A z + B y``, ``x_hat = T*(z)``, with ``T`` and ``T*`` trained on unforced data.

    Parameters
    ----------
    pde_weight: weight of the PDE residual in the encoder's loss.
    """

    name = "autonomous_kkl"

    def __init__(self, pde_weight: float = 1.0) -> None:
        self.pde_weight = pde_weight

    def fit_model(self, context):
        self.model_ = fit_phase1(context, self.pde_weight)

    def estimate(self, t, y, u):
        self.check_fitted()
        return self.model_.estimate(y)
