"""The base class of the KKL estimator plugins: what they record about their fit."""

from __future__ import annotations

from typing import Any

from kkl_bench.estimator import Estimator

NOTHING_SPENT = {"steps": 0, "samples": 0}


class KKLEstimator(Estimator):
    """An estimator built on a Phase-1 model (``self.model_``), maybe with a Phase-2 log (``self.log_``).

    :meth:`fit_report` records the latent rates and how they were chosen, the
    maps' quality on held-out states, the Phase-2 training log, and
    ``spent``: the optimizer steps and samples of Phase 1 (shared by every
    KKL plugin of a system and seed) and of the plugin's own second phase.
    """

    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    """Trained on the task's measurement model (``FitContext.training`` and ``system.h``);
    under a sparse sampling the latent observer is driven by the last measurement held."""

    def fit_report(self) -> dict[str, Any]:
        report = self.model_.report()
        log = getattr(self, "log_", None) or {}
        if log:
            report["training_log"] = log
        report["spent"] = {
            "phase1": self.model_.spent,
            "phase2": log.get("spent", NOTHING_SPENT),
        }
        return report
