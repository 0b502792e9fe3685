"""The base class of the KKL estimator plugins: what they record about their fit."""

from __future__ import annotations

from typing import Any

from kkl_bench.estimator import Estimator


class KKLEstimator(Estimator):
    """An estimator built on a Phase-1 model (``self.model_``), maybe with a Phase-2 log (``self.log_``).

    :meth:`fit_report` records the latent rates and how they were chosen, the
    maps' quality on held-out states, and the Phase-2 training log.
    """

    def fit_report(self) -> dict[str, Any]:
        report = self.model_.report()
        if getattr(self, "log_", None):
            report["training_log"] = self.log_
        return report
