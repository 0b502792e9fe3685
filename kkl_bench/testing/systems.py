"""Conformance checks for a system plugin (``kkl-bench check NAME`` on a system's name).

A system is what every estimator and the simulator read: the checks ask of it what they
rely on. Its declared attributes have the right shapes (``g``, the x0 box); ``f``, ``h``
and their Jacobians keep leading batch axes; the analytic Jacobians agree with central
finite differences at points of the x0 box; ``f`` and ``h`` evaluate torch tensors as
they do numpy arrays, differentiably (the learned estimators train through them);
trajectories from the x0 box under the paper's four regimes stay finite over the
protocol's horizon; and a compiled model, where the system offers one, computes what the
system computes.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from kkl_bench.protocol import DT, N_SAMPLES
from kkl_bench.protocol.compiled import FUNCTION_TYPES
from kkl_bench.protocol.simulate import simulate
from kkl_bench.protocol.system import System
from kkl_bench.registry import regimes, systems
from kkl_bench.testing.kit import NamedChecks, describe, outcomes

POINTS = 16
"""Points of the x0 box the Jacobians and the torch evaluation are checked at."""
STEP = 1e-6
"""Relative step of the central finite differences."""
JACOBIAN_TOLERANCE = 1e-5
"""Largest difference between an analytic Jacobian and the finite differences, relative to
the largest entry of the finite differences (at least 1)."""


class SystemConformance(NamedChecks):
    """The named checks of one system (a registered name or an instance)."""

    def __init__(self, system: str | System) -> None:
        self.system = systems.get(system)() if isinstance(system, str) else system
        rng = np.random.default_rng(0)
        self.points = rng.uniform(self.system.x0_low, self.system.x0_high, (POINTS, self.n_x))

    @property
    def n_x(self) -> int:
        return len(self.system.state_names)

    def check_declared_attributes(self) -> None:
        """``name``, ``state_names``, ``g`` and the x0 box are declared with ``n_x`` entries
        each, the box's lower corner below its upper one, and ``n_y`` at least 1."""
        system = self.system
        assert isinstance(system.name, str) and system.name, "name must be a non-empty string"
        assert self.n_x >= 1, "state_names must name at least one state"
        for attribute in ("g", "x0_low", "x0_high"):
            shape = np.shape(getattr(system, attribute))
            assert shape == (self.n_x,), f"{attribute} has shape {shape}, not ({self.n_x},)"
        below = np.asarray(system.x0_low) < np.asarray(system.x0_high)
        assert below.all(), f"x0_low is not below x0_high in state(s) {np.flatnonzero(~below)}"
        assert system.n_y >= 1, f"n_y must be at least 1, got {system.n_y}"

    def check_shapes(self) -> None:
        """``f``, ``h`` and their Jacobians keep any leading batch axes."""
        system, n_x, n_y = self.system, self.n_x, self.system.n_y
        x = self.points[:6].reshape(2, 3, n_x)
        expected = {
            "f": (system.f, (2, 3, n_x)),
            "h": (system.h, (2, 3, n_y)),
            "f_jacobian": (system.f_jacobian, (2, 3, n_x, n_x)),
            "h_jacobian": (system.h_jacobian, (2, 3, n_y, n_x)),
        }
        for name, (function, shape) in expected.items():
            got = np.shape(function(x))
            assert got == shape, f"{name} of x: (2, 3, {n_x}) has shape {got}, not {shape}"

    def check_f_jacobian(self) -> None:
        """``f_jacobian`` agrees with central finite differences of ``f``."""
        self._compare_jacobian(self.system.f, self.system.f_jacobian, "f")

    def check_h_jacobian(self) -> None:
        """``h_jacobian`` agrees with central finite differences of ``h``."""
        self._compare_jacobian(self.system.h, self.system.h_jacobian, "h")

    def _compare_jacobian(self, function, jacobian, name: str) -> None:
        step = STEP * np.maximum(1.0, np.abs(self.points))
        columns = []
        for j in range(self.n_x):
            shift = np.zeros_like(self.points)
            shift[:, j] = step[:, j]
            difference = function(self.points + shift) - function(self.points - shift)
            columns.append(difference / (2 * step[:, j : j + 1]))
        numeric = np.stack(columns, axis=-1)
        analytic = np.asarray(jacobian(self.points))
        scale = max(1.0, float(np.abs(numeric).max()))
        error = np.abs(analytic - numeric).max(axis=(1, 2)) / scale
        worst = int(error.argmax())
        assert error[worst] <= JACOBIAN_TOLERANCE, (
            f"{name}_jacobian differs from finite differences by {error[worst]:.2e} (relative) "
            f"at x = {self.points[worst].tolist()}: analytic {analytic[worst].tolist()}, "
            f"finite differences {numeric[worst].round(6).tolist()}"
        )

    def check_evaluates_torch_tensors(self) -> None:
        """``f`` and ``h`` of a float64 tensor equal those of the array, and carry gradients
        (write them with array arithmetic, :func:`kkl_bench.protocol.system.stack` and
        :func:`kkl_bench.protocol.system.namespace` for functions such as ``sin``)."""
        import torch

        for name in ("f", "h"):
            function = getattr(self.system, name)
            x = torch.tensor(self.points, requires_grad=True)
            try:
                value = function(x)
                value.sum().backward()
            except Exception as error:
                raise AssertionError(
                    f"{name} fails on a torch tensor ({type(error).__name__}: {error})"
                ) from error
            np.testing.assert_allclose(
                value.detach().numpy(), function(self.points), rtol=1e-10, atol=1e-12,
                err_msg=f"{name} of a torch tensor differs from {name} of the array",
            )  # fmt: skip
            assert x.grad is not None and torch.isfinite(x.grad).all(), f"{name}: no gradient"

    def check_trajectories_stay_finite(self) -> None:
        """Four trajectories from the x0 box under each of the paper's regimes stay finite
        over the protocol's horizon (RK4 at its step, no noise)."""
        rng = np.random.default_rng(1)
        t = DT * np.arange(N_SAMPLES)
        for regime in ("zero", "constant", "sinusoid", "square"):
            x0 = rng.uniform(self.system.x0_low, self.system.x0_high, (4, self.n_x))
            u = regimes.get(regime)().sample(rng, 4, t)
            with np.errstate(all="ignore"):
                data = simulate(self.system, x0, u, DT)
            finite = np.isfinite(data.x).all(axis=(1, 2))
            assert finite.all(), (
                f"under the {regime!r} regime the trajectory from x0 = "
                f"{x0[~finite][0].tolist()} leaves the finite numbers within the horizon"
            )

    def check_compiled_model(self) -> None:
        """Where the system offers a compiled model (:meth:`System.compiled`, what the
        filters' compiled engines run), each of its functions compiles as the type
        :data:`~kkl_bench.protocol.compiled.FUNCTION_TYPES` gives it (C-contiguous float64
        arrays, nothing returned), and its drift, output, their Jacobians and its constraint
        compute what ``f``, ``h``, their Jacobians and ``constrain`` compute at the kit's
        points. A system without one passes: the filters run their reference engine."""
        model = self.system.compiled()
        if model is None:
            return
        for name, function_type in FUNCTION_TYPES.items():
            try:
                getattr(model, name).compile(function_type.signature)
            except Exception as error:
                first_line = str(error).strip().split("\n")[0]
                raise AssertionError(
                    f"compiled().{name} does not compile as {function_type.signature} "
                    f"({type(error).__name__}: {first_line})"
                ) from error
        system, n_x, n_y = self.system, self.n_x, self.system.n_y
        assert model.n_y == n_y, f"compiled().n_y is {model.n_y}, the system's n_y {n_y}"
        np.testing.assert_array_equal(model.g, system.g, err_msg="compiled().g is not g")
        points = np.ascontiguousarray(self.points.T)  # the sweep: (n_x, m)
        m = points.shape[1]
        swept = {
            "drift": (model.p, (n_x, m), system.f),
            "drift_jacobian": (model.p, (n_x, n_x, m), system.f_jacobian),
            "output": (model.q, (n_y, m), system.h),
            "output_jacobian": (model.q, (n_y, n_x, m), system.h_jacobian),
        }
        for name, (parameters, shape, expected) in swept.items():
            out = np.full(shape, np.nan)
            getattr(model, name)(points, parameters, out)
            np.testing.assert_allclose(
                np.moveaxis(out, -1, 0), expected(self.points), rtol=1e-10, atol=1e-12,
                err_msg=f"compiled().{name} differs from the system's",
            )  # fmt: skip
        constrained = points.copy()
        model.constrain(constrained, model.p)
        np.testing.assert_allclose(
            constrained.T, system.constrain(self.points), rtol=1e-12, atol=0,
            err_msg="compiled().constrain differs from the system's constrain",
        )  # fmt: skip


def run_system_checks(system: str | System) -> Iterator[tuple[str, BaseException | None]]:
    """Run every check on ``system``; yields ``(name, None)`` on success, ``(name, error)``
    on failure."""
    return outcomes(SystemConformance(system).checks())


def check_system(system: str | System) -> None:
    """Run every check on ``system``; raise one AssertionError listing all failures."""
    failures = [f"{name}: {describe(error)}" for name, error in run_system_checks(system) if error]
    if failures:
        raise AssertionError(f"{len(failures)} system check(s) failed:\n" + "\n".join(failures))
