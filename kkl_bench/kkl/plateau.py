"""The plateau rule every learned training ends by (protocol section 6.5).

A training measures its validation error every ``validate_every`` optimizer
steps. A measurement *progresses* when it is more than ``plateau_tolerance``
(relative) below the error of the last measurement that progressed (so a slow,
steady fall adds up to progress). After ``plateau_patience`` measurements
in a row without progress the learning rate is multiplied by ``lr_factor`` (and
the count starts again); the plateau that follows the ``plateau_reductions``-th
reduction stops the training. A training that reaches its cap of steps first
stops there; one whose validation error is not finite stops at once. Either way
the parameters of the best measurement are restored at the end, so the model
kept is the training's best on validation, and the fit report says at which
step it was measured (:attr:`Plateau.best_step`) and why the training stopped
(:data:`~kkl_bench.support.convergence.STOPPED_BY`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from kkl_bench.support.convergence import STOPPED_BY

PLATEAU, CAP, DIVERGED = STOPPED_BY
"""Why a training stopped (the verdicts they read as:
:data:`~kkl_bench.support.convergence.STOPPED_BY`)."""


@dataclass(frozen=True)
class PlateauRule:
    """The rule's settings (budget keys of a profile, read with
    :func:`kkl_bench.kkl.config.from_budget`)."""

    validate_every: int = 200
    """Optimizer steps between two validation measurements."""
    plateau_patience: int = 5
    """Measurements in a row without progress that make a plateau."""
    plateau_tolerance: float = 0.01
    """Relative fall below the best error that counts as progress."""
    plateau_reductions: int = 5
    """Learning-rate reductions before a plateau stops the training."""
    lr_factor: float = 0.5
    """What a reduction multiplies the learning rate by."""

    def __post_init__(self) -> None:
        for name in ("validate_every", "plateau_patience"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)}")
        if not 0.0 <= self.plateau_tolerance < 1.0:
            raise ValueError(f"plateau_tolerance must be in [0, 1), got {self.plateau_tolerance}")
        if self.plateau_reductions < 0:
            raise ValueError(f"plateau_reductions must be >= 0, got {self.plateau_reductions}")
        if not 0.0 < self.lr_factor < 1.0:
            raise ValueError(f"lr_factor must be in (0, 1), got {self.lr_factor}")


CONTINUE, REDUCE, STOP = "continue", "reduce", "stop"


class Plateau:
    """The rule's state along one training of ``parameters`` under ``optimizer``.

    :meth:`measure` takes each validation error and lowers the optimizer's learning
    rate or stops the training as the rule says; it keeps a copy of the parameters at
    the best error, which :meth:`restore_best` puts back.
    """

    def __init__(
        self,
        rule: PlateauRule,
        parameters: list[torch.nn.Parameter],
        optimizer: torch.optim.Optimizer | None = None,
    ) -> None:
        self.rule = rule
        self.parameters = parameters
        self.optimizer = optimizer
        self.best_error = math.inf
        self.best_step = 0
        self.best_state: list[torch.Tensor] | None = None
        self.reference = math.inf
        """The error of the last measurement that progressed."""
        self.without_progress = 0
        self.reductions: list[int] = []
        """Steps at which the learning rate was reduced."""
        self.stopped: str | None = None

    def measure(self, step: int, error: float) -> str:
        """Take the validation ``error`` measured after ``step`` optimizer steps; returns
        :data:`CONTINUE`, :data:`REDUCE` (the learning rate was just lowered) or
        :data:`STOP` (:attr:`stopped` says why)."""
        if not math.isfinite(error):
            self.stopped = DIVERGED
            return STOP
        if error < self.best_error:
            self.best_error, self.best_step = error, step
            self.best_state = [p.detach().clone() for p in self.parameters]
        if error < (1.0 - self.rule.plateau_tolerance) * self.reference:
            self.reference, self.without_progress = error, 0
        else:
            self.without_progress += 1
        if self.without_progress < self.rule.plateau_patience:
            return CONTINUE
        if len(self.reductions) == self.rule.plateau_reductions:
            self.stopped = PLATEAU
            return STOP
        self.without_progress = 0
        self.reductions.append(step)
        if self.optimizer is not None:
            for group in self.optimizer.param_groups:
                group["lr"] *= self.rule.lr_factor
        return REDUCE

    def reach_cap(self) -> None:
        """Record that the training reached its cap of steps before the rule stopped it."""
        if self.stopped is None:
            self.stopped = CAP

    def restore_best(self) -> None:
        """Put the parameters of the best measurement back (nothing if none was finite)."""
        if self.best_state is None:
            return
        with torch.no_grad():
            for parameter, value in zip(self.parameters, self.best_state, strict=True):
                parameter.copy_(value)

    def log(self) -> dict[str, Any]:
        """What a fit report records of the rule: why the training stopped, the step and
        error of the model kept, the steps of the learning-rate reductions."""
        return {
            "stopped": self.stopped,
            "best_step": self.best_step,
            "best_error": self.best_error,
            "lr_reductions": list(self.reductions),
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed training needs to go on as if uninterrupted."""
        return {
            "best_error": self.best_error,
            "best_step": self.best_step,
            "best_state": self.best_state,
            "reference": self.reference,
            "without_progress": self.without_progress,
            "reductions": list(self.reductions),
            "stopped": self.stopped,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.best_error = state["best_error"]
        self.best_step = state["best_step"]
        self.best_state = state["best_state"]
        self.reference = state["reference"]
        self.without_progress = state["without_progress"]
        self.reductions = list(state["reductions"])
        self.stopped = state["stopped"]
