"""The base class of the KKL estimator plugins: how they are fitted and what they record."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.fitting.calibration import calibrated_context, calibration_report

NOTHING_SPENT = {"steps": 0, "samples": 0}
LARGEST_LATENT = 1620
"""The largest latent state the KKL rows are fitted for here: Lorenz-96 with 40 states
(``n_z = n_y (2 n_x + 1)`` grows fourfold when the state doubles; protocol section 8)."""


class KKLEstimator(Estimator):
    """An estimator built on a Phase-1 model (``self.model_``), maybe with a Phase-2 log (``self.log_``).

    Subclasses implement :meth:`fit_model`. Given logged data of a true plant
    (the ``+logged`` rows of the ``mismatch`` track), the observer is trained
    on the nominal model calibrated on them (:mod:`kkl_bench.fitting.calibration`): its
    training data are simulated by the calibrated model, as an engineer who
    calibrated first would train it. :meth:`fit_report` records the latent
    rates and how they were chosen, the maps' quality on held-out states, the
    Phase-2 training log, the calibrated parameters if any, and ``spent``: the
    optimizer steps and samples of Phase 1 (shared by every KKL plugin of a
    system, measurement model and seed) and of the plugin's own second phase.
    """

    family = "learned"
    uses_logged_data = True
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model (``FitContext.training`` and ``system.h``);
    under a sparse sampling the latent observer is driven by the last measurement held."""

    def unsupported_reason(self, system, measurement):
        if system.n_z > LARGEST_LATENT:
            return (
                f"not affordable here: its latent state would have n_z = {system.n_z} "
                f"components (n_y (2 n_x + 1)), beyond the {LARGEST_LATENT} of the largest "
                "system the KKL rows are fitted for on this machine"
            )
        return super().unsupported_reason(system, measurement)

    def fit(self, context: FitContext):
        context = calibrated_context(context)
        self.fit_model(context)
        return super().fit(context)

    @abstractmethod
    def fit_model(self, context: FitContext) -> None:
        """Train (or load from the cache) the observer for ``context``."""

    def adopt_choices(self, report: dict[str, Any]) -> None:
        """The injection gain chosen on validation data (``training_log.injection_gain``
        of ``injection_kkl`` and of ``static_hyperkkl[guard=True]``): a gain of zero skips
        the injection's arithmetic."""
        gain = (report.get("training_log") or {}).get("injection_gain")
        if gain is not None:
            self.gain_ = gain

    def fit_report(self) -> dict[str, Any]:
        report = self.model_.report()
        log = getattr(self, "log_", None) or {}
        if log:
            report["training_log"] = log
        report["spent"] = {
            "phase1": self.model_.spent,
            "phase2": log.get("spent", NOTHING_SPENT),
        }
        return {**report, **calibration_report(self.check_fitted())}
