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
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar, Self

import numpy as np

from kkl_bench.measurement import FEATURES, MeasurementModel, with_scale
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.protocol.system import System
from kkl_bench.support.cache import default_cache_dir
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
        (:mod:`kkl_bench.support.devices`); estimates always run on the CPU.
    logged_data: trajectories logged on the true plant (``t, u, x, y``) of a ``mismatch``
        task, given only to estimators that declare ``uses_logged_data``, else None. The
        plant differs from ``system`` (the nominal model) and from what ``training``
        simulates; see ``docs/protocol.md`` section 7.5.
    measurement: how the states are observed (:mod:`kkl_bench.measurement`): the sensor
        (already in ``system.h`` and ``system.h_jacobian``), the sampling (``y`` is NaN at
        the samples not observed), the noise law (``log_density``, ``variance``; its scale
        is ``sigma_v``). None (default): the protocol's, ``h(x)`` plus Gaussian noise at
        every sample. Differs from it on a track fitted per task (``hard``) only.
    x0_box: ``(low, high)``, each ``(n_x,)``: the box initial states come from, where it
        is not the system's (a ``+truth`` fit on ``far-init``); None (default): the system's.
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
    measurement: MeasurementModel | None = None
    x0_box: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        measurement = with_scale(self.measurement, self.sigma_v, "FitContext")
        object.__setattr__(self, "measurement", measurement)

    @property
    def x0_low(self) -> np.ndarray:
        """The lower corner ``(n_x,)`` of the box initial states come from (``system.x0_low``
        unless ``x0_box`` says otherwise)."""
        return self.system.x0_low if self.x0_box is None else self.x0_box[0]

    @property
    def x0_high(self) -> np.ndarray:
        """The upper corner ``(n_x,)`` of that box."""
        return self.system.x0_high if self.x0_box is None else self.x0_box[1]


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
    supported_measurements: the ways in which ``FitContext.measurement`` may differ from
        the protocol's that the estimator handles: any of ``"sensor"`` (a sensor in
        ``system.h``), ``"sampling"`` (NaN measurements between observed samples) and
        ``"noise"`` (a non-Gaussian law). Default none: on a task that needs another,
        its cells are recorded as ``unsupported`` with the reason
        ``unsupported_reason(system, measurement)`` gives; override that method to
        refuse systems the method cannot express (``ring_observer`` refuses systems
        without ``System.ring``).
    family: what the estimator is (:mod:`kkl_bench.families`): ``"model-based"`` (uses
        the model, trains nothing beyond choosing settings on validation streams),
        ``"learned"`` (trains on data) or ``"limit"`` (approximates the exact posterior
        mean). Default None: not declared, read as ``"learned"`` and marked as undeclared
        by ``kkl-bench list``. Every table that separates learned rows from filters
        reads it.
    bayes_limit: whether the estimator approximates the exact posterior mean (the
        particle filter). On a track whose tasks differ from the model it is fitted
        with (noise, initial box), it is also fitted with each task's truth and
        published as ``<name>+truth``: the limit no estimator can beat there.
    check_budget: budget keys the conformance kit (``kkl-bench check``) fits the
        estimator with, over the ``quick`` profile's budget (default none): a learned
        plugin sets small ones, so that checking it takes a minute, not its training.
    """

    name: ClassVar[str] = ""
    family: ClassVar[str | None] = None
    uses_seed: ClassVar[bool] = True
    uses_logged_data: ClassVar[bool] = False
    supported_measurements: ClassVar[frozenset[str]] = frozenset()
    bayes_limit: ClassVar[bool] = False
    check_budget: ClassVar[Mapping[str, Any]] = MappingProxyType({})

    def unsupported_reason(self, system: System, measurement: MeasurementModel) -> str | None:
        """Why the estimator cannot be fitted for ``system`` observed through
        ``measurement``, or None if it can. The default: a measurement model that differs
        from the protocol's in an aspect not in :attr:`supported_measurements`; a plugin
        that needs a kind of system (a ring, say) adds its own reason."""
        missing = [f for f in FEATURES if f in measurement.features - self.supported_measurements]
        if not missing:
            return None
        return (
            f"handles no measurement model with another {' or '.join(missing)} than the "
            f"protocol's (needs: {measurement.describe()})"
        )

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

    def adopt_choices(self, report: dict[str, Any]) -> None:
        """Take from a fitted estimator's :meth:`fit_report` the choices its fit made from
        data that change what :meth:`estimate` computes (not the learned weights), so that
        a model of the same structure, not trained, runs the same arithmetic: the scaling
        study times such models (protocol section 8). The default: none to take."""
        return None

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
