"""The base class of the KKL estimator plugins: how they are fitted and what they record."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

from kkl_bench.calibration import calibrated_context, calibration_report
from kkl_bench.estimator import Estimator, FitContext

NOTHING_SPENT = {"steps": 0, "samples": 0}


class KKLEstimator(Estimator):
    """An estimator built on a Phase-1 model (``self.model_``), maybe with a Phase-2 log (``self.log_``).

    Subclasses implement :meth:`fit_model`. Given logged data of a true plant
    (the ``+logged`` rows of the ``mismatch`` track), the observer is trained
    on the nominal model calibrated on them (:mod:`kkl_bench.calibration`): its
    training data are simulated by the calibrated model, as an engineer who
    calibrated first would train it. :meth:`fit_report` records the latent
    rates and how they were chosen, the maps' quality on held-out states, the
    Phase-2 training log, the calibrated parameters if any, and ``spent``: the
    optimizer steps and samples of Phase 1 (shared by every KKL plugin of a
    system, measurement model and seed) and of the plugin's own second phase.
    """

    uses_logged_data = True
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model (``FitContext.training`` and ``system.h``);
    under a sparse sampling the latent observer is driven by the last measurement held."""

    def fit(self, context: FitContext):
        context = calibrated_context(context)
        self.fit_model(context)
        return super().fit(context)

    @abstractmethod
    def fit_model(self, context: FitContext) -> None:
        """Train (or load from the cache) the observer for ``context``."""

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
