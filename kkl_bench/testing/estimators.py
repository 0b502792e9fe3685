"""Conformance kit for estimator plugins, after scikit-learn's ``check_estimator``.

Every registered estimator is run through these checks by kkl-bench's own
tests; a plugin author runs them on theirs::

    from kkl_bench.testing import check_estimator
    check_estimator("my_estimator")          # raises AssertionError listing failures

or from the shell: ``kkl-bench check my_estimator``. Each check is small and
named; :func:`estimator_checks` yields them for ``pytest.mark.parametrize``.

The checks fit the estimator once per system (by default :data:`CHECK_SYSTEMS`:
a two-state and a three-state system) with the ``quick`` profile's budget updated with
the estimator's ``check_budget``,
inside :func:`sealed_test_streams` (so reading a test set fails), and run it
on short forced trajectories from a stream of its own. Every fit gets a fresh, empty cache directory, so the determinism
check really trains twice. An estimator that declares ``uses_logged_data``
is also fitted on the ``mismatch`` track's logged data, with the true
plants' parameter errors sealed as well.
"""

from __future__ import annotations

import dataclasses
import functools
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kkl_bench import variants
from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.measurement import FEATURES, Identity, MeasurementModel, NoiseLaw, Quantized
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.protocol.streams import sealed_test_streams
from kkl_bench.registry import regimes, systems
from kkl_bench.run.spec import FitConditions, conditioned_context
from kkl_bench.suite.plants import logged_data
from kkl_bench.suite.task import get_profile
from kkl_bench.suite.tracks import get_track
from kkl_bench.testing.kit import NamedChecks, describe, outcomes
from kkl_bench.training import TrainingData

CHECK_STEPS = 200
"""Samples per check trajectory (10 s)."""
CHECK_BATCH = 3


class Conformance(NamedChecks):
    """Runs the named checks on one estimator (fitted once, lazily).

    Parameters
    ----------
    estimator: registry name or variant (``static_hyperkkl[guard=True]``), or an
        unfitted estimator instance.
    system: registry name of the system to check on (default: the first of
        :func:`check_systems`).
    budget: training budget for ``fit`` (default: the quick profile's for this estimator,
        updated with its ``check_budget``).
    """

    def __init__(
        self,
        estimator: str | Estimator,
        system: str | None = None,
        budget: dict[str, Any] | None = None,
    ) -> None:
        if isinstance(estimator, str):
            self.name = estimator
            self.prototype = variants.build(estimator)
            budget_name = variants.base_name(estimator)
        else:
            self.name = type(estimator).__name__
            self.prototype = estimator
            budget_name = self.name
        model = systems.get(system or check_systems(self.prototype)[0])()
        self.context = FitContext(
            system=model,
            dt=DT,
            n_samples=N_SAMPLES,
            sigma_w=SIGMA_W,
            sigma_v=SIGMA_V,
            training=TrainingData(model, DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed=0),
            seed=0,
            profile="quick",
            budget=check_budget(self.prototype, budget_name) if budget is None else budget,
            cache_dir=self.fresh_cache(),
        )
        self.data: Trajectories = self.context.training.simulate(
            regimes.get("sinusoid")(), CHECK_BATCH, stream="conformance", n_samples=CHECK_STEPS
        )

    def fresh_cache(self):
        """A new empty cache directory, removed with this object."""
        directory = tempfile.TemporaryDirectory(prefix="kkl-bench-check-")
        self._directories = [*getattr(self, "_directories", []), directory]
        return Path(directory.name)

    @functools.cached_property
    def fitted(self) -> Estimator:
        with sealed_test_streams():
            return self.prototype.clone().fit(self.context)

    def estimate(
        self, estimator: Estimator, y: np.ndarray | None = None, u: np.ndarray | None = None
    ) -> np.ndarray:
        y = self.data.y.copy() if y is None else y
        u = self.data.u.copy() if u is None else u
        with sealed_test_streams():
            return np.asarray(estimator.estimate(self.data.t.copy(), y, u), dtype=float)

    @functools.cached_property
    def x_hat(self) -> np.ndarray:
        return self.estimate(self.fitted)

    def check_params_and_clone(self) -> None:
        """``get_params`` returns the ``__init__`` keywords; ``clone`` rebuilds an equal, unfitted copy."""
        params = self.prototype.get_params()
        assert set(params) == set(type(self.prototype).param_names()), (
            f"get_params() keys {sorted(params)} differ from __init__ keywords {type(self.prototype).param_names()}"
        )
        clone = self.prototype.clone()
        assert type(clone) is type(self.prototype) and clone.get_params().keys() == params.keys()
        assert getattr(clone, "context_", None) is None, "clone() must return an unfitted estimator"

    def check_fit_returns_self(self) -> None:
        """``fit`` returns the estimator itself."""
        estimator = self.prototype.clone()
        with sealed_test_streams():
            returned = estimator.fit(self.context)
        assert returned is estimator, f"fit() returned {returned!r}, not the estimator"

    def check_output_shape_and_finite(self) -> None:
        """``estimate`` returns finite ``(batch, steps, n_x)`` estimates."""
        expected = self.data.x.shape
        assert self.x_hat.shape == expected, (
            f"estimate returned shape {self.x_hat.shape}; expected {expected}"
        )
        assert np.isfinite(self.x_hat).all(), "estimate has NaN or inf on an easy forced trajectory"

    def check_causal(self) -> None:
        """Changing ``y`` and ``u`` after step k leaves estimates up to k unchanged."""
        k = CHECK_STEPS // 2
        y, u = self.data.y.copy(), self.data.u.copy()
        y[:, k + 1 :] += 0.5
        u[:, k + 1 :] = -u[:, k + 1 :] + 0.3
        perturbed = self.estimate(self.fitted, y, u)
        assert np.allclose(
            perturbed[:, : k + 1], self.x_hat[:, : k + 1], rtol=1e-6, atol=1e-9, equal_nan=True
        ), f"estimates up to step {k} changed when only later measurements and inputs changed"

    def check_batch_independent(self) -> None:
        """A trajectory's estimate does not depend on the other trajectories of the batch."""
        alone = np.concatenate(
            [
                self.estimate(
                    self.fitted, self.data.y[i : i + 1].copy(), self.data.u[i : i + 1].copy()
                )
                for i in range(CHECK_BATCH)
            ]
        )
        # float32 networks in a feedback loop (an injection evaluated at the estimate)
        # turn batch-size-dependent BLAS rounding (1e-7) into differences of ~1e-5
        assert np.allclose(alone, self.x_hat, rtol=1e-4, atol=1e-4, equal_nan=True), (
            "estimates change with the rest of the batch"
        )

    def check_deterministic(self) -> None:
        """Fitting again with the same context and seed (and an empty cache) gives the same estimates."""
        context = dataclasses.replace(self.context, cache_dir=self.fresh_cache())
        with sealed_test_streams():
            again = self.prototype.clone().fit(context)
        assert np.allclose(
            self.estimate(again), self.x_hat, rtol=1e-6, atol=1e-9, equal_nan=True
        ), "two fits with the same seed gave different estimates"

    def check_does_not_modify_inputs(self) -> None:
        """``estimate`` leaves its ``t``, ``y`` and ``u`` arguments untouched."""
        t, y, u = self.data.t.copy(), self.data.y.copy(), self.data.u.copy()
        with sealed_test_streams():
            self.fitted.estimate(t, y, u)
        assert (
            np.array_equal(t, self.data.t)
            and np.array_equal(y, self.data.y)
            and np.array_equal(u, self.data.u)
        ), "estimate modified its input arrays"

    def check_fits_on_logged_data_without_the_true_plant(self) -> None:
        """An estimator that ``uses_logged_data`` fits on a true plant's logged data (the
        ``mismatch`` track's 25 % plant; its sensor plant for other systems) without
        asking for that plant's parameters, which are sealed like the test streams; its
        estimates are finite."""
        if not type(self.prototype).uses_logged_data:
            return
        track, system = get_track("mismatch"), self.context.system.name
        # systems off the track have no declared parameter errors: their sensor plant
        task = "params25-sinusoid" if system in track.systems else "sensor-sinusoid"
        logged = logged_data(system, track.task(task).plant, track.name, SIGMA_W, SIGMA_V)
        # the nominal fit's cache: only the fine-tuning on the logged data trains anew
        context = dataclasses.replace(self.context, logged_data=logged)
        with sealed_test_streams():
            fitted = self.prototype.clone().fit(context)
        assert np.isfinite(self.estimate(fitted)).all(), (
            "estimate has NaN or inf after a fit with logged data"
        )

    def check_handles_the_measurement_models_it_declares(self) -> None:
        """``supported_measurements`` names only known aspects, and on a measurement model
        with all of them (a quantizer of step 0.05, every third sample, Student-t noise
        with 3 degrees of freedom) the estimator fits and its estimates are finite."""
        declared = type(self.prototype).supported_measurements
        unknown = sorted(declared - set(FEATURES))
        assert not unknown, f"supported_measurements names {unknown}; valid: {', '.join(FEATURES)}"
        if not declared:
            return
        measurement = MeasurementModel(
            Quantized(0.05) if "sensor" in declared else Identity(),
            3 if "sampling" in declared else 1,
            NoiseLaw("student-t", SIGMA_V, dof=3.0) if "noise" in declared else NoiseLaw(),
        )
        context = conditioned_context(
            self.context.system.name,
            0,
            FitConditions(measurement),
            profile="quick",
            budget=self.context.budget,
            cache_dir=self.fresh_cache(),
        )
        data = context.training.simulate(
            regimes.get("sinusoid")(), CHECK_BATCH, stream="conformance", n_samples=CHECK_STEPS
        )
        with sealed_test_streams():
            fitted = self.prototype.clone().fit(context)
            x_hat = np.asarray(fitted.estimate(data.t, data.y, data.u), dtype=float)
        assert np.isfinite(x_hat).all(), (
            f"estimate has NaN or inf under a measurement model it declares it handles "
            f"({measurement.describe()})"
        )

    def check_does_not_read_test_sets(self) -> None:
        """``fit`` and ``estimate`` never ask for a test stream (they run sealed; see the module doc)."""
        self.x_hat  # noqa: B018 - fitting and estimating inside sealed_test_streams() is the check


def check_budget(estimator: Estimator, name: str) -> dict[str, Any]:
    """The budget a check fits ``estimator`` (registered as ``name``) with: the ``quick``
    profile's for it, updated with its ``check_budget``."""
    return {**get_profile("quick").budget_for(name), **estimator.check_budget}


def estimator_checks(
    estimator: str | Estimator, system: str | None = None, budget: dict[str, Any] | None = None
) -> Iterator[tuple[str, Callable[[], None]]]:
    """The named checks for ``estimator``; they share one fit."""
    return Conformance(estimator, system, budget).checks()


CHECK_SYSTEMS = ("duffing", "lorenz")
"""The systems :func:`check_estimator` and ``kkl-bench check`` use by default: one with two
states, one with three (a plugin that assumes a state dimension fails one of them)."""


def check_systems(estimator: str | Estimator) -> tuple[str, ...]:
    """The systems to check ``estimator`` on by default: those of :data:`CHECK_SYSTEMS` it
    supports (:meth:`~kkl_bench.estimator.Estimator.unsupported_reason`), or, for a
    plugin that supports neither (a ring observer), the first two registered systems it
    supports."""
    prototype = variants.build(estimator) if isinstance(estimator, str) else estimator

    def supported(name: str) -> bool:
        return prototype.unsupported_reason(systems.get(name)(), MeasurementModel()) is None

    chosen = tuple(name for name in CHECK_SYSTEMS if supported(name))
    chosen = chosen or tuple(name for name in systems.names() if supported(name))[:2]
    if not chosen:
        raise ValueError(f"{type(prototype).__name__} supports no registered system")
    return chosen


def _systems(estimator: str | Estimator, systems: str | Sequence[str] | None) -> tuple[str, ...]:
    if systems is None:
        return check_systems(estimator)
    return (systems,) if isinstance(systems, str) else tuple(systems)


def run_checks(
    estimator: str | Estimator,
    systems: str | Sequence[str] | None = None,
    budget: dict[str, Any] | None = None,
) -> Iterator[tuple[str, str, BaseException | None]]:
    """Run every check on each of ``systems`` (default :func:`check_systems`; one fit per
    system); yields ``(system, name, None)`` on success, ``(system, name, error)`` on
    failure. A fit that raises fails every check of its system with that error. An
    unknown estimator or system raises before any check."""
    for system in _systems(estimator, systems):
        for name, error in outcomes(estimator_checks(estimator, system, budget)):
            yield system, name, error


def check_estimator(
    estimator: str | Estimator,
    systems: str | Sequence[str] | None = None,
    budget: dict[str, Any] | None = None,
) -> None:
    """Run every check on each of ``systems`` (default :func:`check_systems`); raise one
    AssertionError listing all failures."""
    failures = [
        f"{system}: {name}: {describe(error)}"
        for system, name, error in run_checks(estimator, systems, budget)
        if error
    ]
    if failures:
        raise AssertionError(
            f"{len(failures)} conformance check(s) failed:\n" + "\n".join(failures)
        )
