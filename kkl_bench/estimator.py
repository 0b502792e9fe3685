"""The estimator interface every plugin implements.

An estimator is a state observer. The harness builds it from keyword
hyperparameters, calls :meth:`Estimator.fit` once per system with a
:class:`FitContext`, then :meth:`Estimator.estimate` on each test set::

    x_hat = estimator.fit(context).estimate(t, y, u)

``t: (steps,)`` sample times in s, ``y: (batch, steps, n_y)`` measurements,
``u: (batch, steps, 1)`` held input samples, ``x_hat: (batch, steps, n_x)``.
Estimates must be causal (``x_hat[:, k]`` uses ``y[:, :k+1]`` and
``u[:, :k+1]`` only), independent across the batch, and must not depend on
anything but the context, the seed and the arguments.
"""

from __future__ import annotations

import copy
import inspect
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np

from kkl_bench.cache import default_cache_dir
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.protocol.system import System
from kkl_bench.training import TrainingData


@dataclass(frozen=True)
class FitContext:
    """Everything an estimator may know when it is fitted.

    Attributes
    ----------
    system: the model (``f``, ``g``, ``h``, Jacobians, x0 box).
    dt: sampling step (s).
    n_samples: samples per test trajectory.
    sigma_w: standard deviation of the process noise added to every state after each
        sample's RK4 step (``docs/protocol.md`` section 1).
    sigma_v: standard deviation of the measurement noise on ``y``.
    training: generator of training trajectories (never the test streams).
    seed: the run's seed.
    profile: name of the profile being run (``"quick"``, ``"standard"``).
    budget: the profile's training budget for this estimator (free-form keys).
    cache_dir: where the estimator may cache trained models.
    device: where torch estimators train: ``auto``, ``cpu`` or ``cuda``
        (:mod:`kkl_bench.devices`); estimates always run on the CPU.
    logged_data: trajectories logged on the true plant (``t, u, x, y``) of a ``mismatch``
        task, given only to estimators that declare ``uses_logged_data``, else None. The
        plant differs from ``system`` (the nominal model) and from what ``training``
        simulates; see ``docs/protocol.md`` section 7.5.
    """

    system: System
    dt: float
    n_samples: int
    sigma_w: float
    sigma_v: float
    training: TrainingData
    seed: int = 0
    profile: str = "quick"
    budget: dict[str, Any] = field(default_factory=dict)
    cache_dir: Path = field(default_factory=default_cache_dir)
    logged_data: Trajectories | None = None
    device: str = "cpu"

    @property
    def x0_low(self) -> np.ndarray:
        """``system.x0_low``: the lower corner ``(n_x,)`` of the box initial states come from."""
        return self.system.x0_low

    @property
    def x0_high(self) -> np.ndarray:
        """``system.x0_high``: the upper corner ``(n_x,)`` of that box."""
        return self.system.x0_high


class NotFittedError(RuntimeError):
    """``estimate`` was called before ``fit``."""


class Estimator(ABC):
    """Base class of state estimators.

    Subclasses take their hyperparameters as keyword arguments of
    ``__init__`` and store them unchanged under the same names (so
    :meth:`get_params` and :meth:`clone` work); state learned in ``fit`` ends
    in ``_``.

    Attributes
    ----------
    name: the registry name, for messages (optional; the registry knows it).
    uses_seed: whether the fitted estimator depends on the training seed (default
        True). One that does not (a filter given the model) is run with one seed only,
        however many are asked.
    uses_logged_data: whether ``fit`` can use ``FitContext.logged_data`` (default False).
        On the ``mismatch`` track such an estimator is fitted a second time per true
        plant, with its logged data, and published as a row of its own
        (``<name>+logged``).
    """

    name: ClassVar[str] = ""
    uses_seed: ClassVar[bool] = True
    uses_logged_data: ClassVar[bool] = False

    def fit(self, context: FitContext) -> Self:
        """Prepare for ``context.system``; the default only records the context."""
        self.context_ = context
        return self

    @abstractmethod
    def estimate(self, t: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Causal state estimates ``(batch, steps, n_x)`` from ``t: (steps,)``,
        ``y: (batch, steps, n_y)`` and ``u: (batch, steps, 1)``."""

    def fit_report(self) -> dict[str, Any]:
        """Facts about the fitted model worth keeping with every result (JSON-able).

        For example the chosen latent eigenvalues or the map-quality numbers of
        a learned observer. The default reports nothing.
        """
        return {}

    def check_fitted(self) -> FitContext:
        """The fit context, or a :class:`NotFittedError` naming the estimator."""
        context = getattr(self, "context_", None)
        if context is None:
            raise NotFittedError(f"{type(self).__name__} is not fitted; call fit(context) first")
        return context

    @classmethod
    def param_names(cls) -> list[str]:
        signature = inspect.signature(cls.__init__)
        kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        return [
            name
            for name, parameter in signature.parameters.items()
            if name != "self" and parameter.kind in kinds
        ]

    def get_params(self) -> dict[str, Any]:
        """The hyperparameters passed to ``__init__``."""
        return {name: getattr(self, name) for name in self.param_names()}

    def clone(self) -> Self:
        """An unfitted copy with the same hyperparameters."""
        return type(self)(**copy.deepcopy(self.get_params()))

    def __repr__(self) -> str:
        params = ", ".join(f"{key}={value!r}" for key, value in self.get_params().items())
        return f"{type(self).__name__}({params})"
