"""The systems beyond the paper's: outputs, torch evaluation, known behaviour."""

from dataclasses import replace

import numba
import numpy as np
import pytest
import torch
from kkl_bench.estimators.filters import kalman_unrolled
from kkl_bench.systems.lorenz96 import lorenz96

from kkl_bench.kkl.latent import LatentObserver, latent_matrices, spread_eigenvalues
from kkl_bench.protocol import DT
from kkl_bench.protocol.simulate import simulate
from kkl_bench.registry import systems
from kkl_bench.testing import check_estimator
from kkl_bench.testing.systems import check_system, run_system_checks
from tests.budgets import few_steps

NEW_SYSTEMS = [
    "fitzhugh_nagumo",
    "chua",
    "lorenz96-n5",
    "lorenz96-n10",
    "lorenz96-n20",
    "lorenz96-n40",
    "lorenz96-n80",
    "lorenz96-n160",
]
LARGE = ("lorenz96-n80", "lorenz96-n160")
"""Too slow for the default run's conformance kit (the UKF's 321 sigma points at n = 160);
they are Lorenz-96 like the smaller sizes, which it covers."""
KIT_IN_THE_DEFAULT_RUN = ("lorenz96-n5",)
"""The system whose filters' kit runs without ``--exhaustive``: several outputs, the generic
kernels. The others' kits compile kernels for these systems alone (80-90 s each from empty
caches): FitzHugh-Nagumo takes the unrolled kernels the paper's oscillators take, Chua's
piecewise drift the generic ones (:func:`test_chua_takes_the_generic_filter_kernels_and_fitzhugh_nagumo_the_unrolled`),
Lorenz-96 from n = 20 the large-system kernels, which
``tests/test_filter_engines.py`` compares with filterpy at n = 20."""


@pytest.mark.parametrize("name", NEW_SYSTEMS)
def test_torch_and_numpy_evaluate_the_same_model(name):
    system = systems.get(name)()
    x = np.random.default_rng(0).uniform(system.x0_low, system.x0_high, (3, system.n_x))
    u = np.array([0.0, 0.5, -1.0])
    x_torch = torch.as_tensor(x)
    np.testing.assert_allclose(
        system.vector_field(x_torch, torch.as_tensor(u)).numpy(), system.vector_field(x, u)
    )
    np.testing.assert_allclose(system.h(x_torch).numpy(), system.h(x))
    assert system.h(x).shape == (3, system.n_y)


@pytest.mark.parametrize("name", NEW_SYSTEMS)
def test_h_jacobian_matches_finite_differences(name):
    system = systems.get(name)()
    x = np.random.default_rng(1).uniform(-2, 2, (4, system.n_x))
    for j in range(system.n_x):
        step = np.zeros(system.n_x)
        step[j] = 1e-6
        column = (system.h(x + step) - system.h(x - step)) / 2e-6
        np.testing.assert_allclose(system.h_jacobian(x)[..., j], column, atol=1e-8)


def test_lorenz96_measures_every_other_state_and_names_its_size():
    system = systems.get("lorenz96-n5")()
    assert (system.name, system.n_x, system.n_y, system.n_z) == ("lorenz96-n5", 5, 3, 33)
    np.testing.assert_array_equal(system.h(np.arange(5.0)), [0.0, 2.0, 4.0])
    assert systems.get("lorenz96-n40")().n_z == 20 * 81
    with pytest.raises(ValueError, match="at least 4 states, got n = 3"):
        lorenz96(3)


def test_lorenz96_rests_at_its_equilibrium_and_is_translation_invariant():
    system = lorenz96(12)()
    np.testing.assert_allclose(system.f(np.full(12, 8.0)), 0.0)
    x = np.random.default_rng(2).normal(size=12)
    np.testing.assert_allclose(system.f(np.roll(x, 3)), np.roll(system.f(x), 3))


def test_fitzhugh_nagumo_spikes_with_the_known_period():
    """Unforced, it spikes on a limit cycle of period ~39.5 model time units, 7.9 s on the
    protocol's clock (one second is five model time units)."""
    system = systems.get("fitzhugh_nagumo")()
    steps = 2000  # 100 s
    v = simulate(system, np.array([[0.0, 0.0]]), np.zeros((1, steps)), DT).x[0, :, 0]
    upward = np.flatnonzero((v[:-1] < 0) & (v[1:] >= 0))[2:]  # past the transient
    assert np.mean(np.diff(upward)) * DT == pytest.approx(39.5 / 5, rel=0.02)


def test_chua_stays_on_the_double_scroll():
    system = systems.get("chua")()
    x = simulate(system, np.array([[0.1, 0.0, 0.0]]), np.zeros((1, 2000)), DT).x[0]
    assert np.abs(x[:, 0]).max() < 3.0
    assert x[1000:, 0].min() < -1.0 < 1.0 < x[1000:, 0].max()  # visits both scrolls


def test_chua_takes_the_generic_filter_kernels_and_fitzhugh_nagumo_the_unrolled():
    """Chua's drift branches on the state: no straight-line code to unroll."""
    assert not kalman_unrolled.unrollable(systems.get("chua")().compiled())
    assert kalman_unrolled.unrollable(systems.get("fitzhugh_nagumo")().compiled())


def test_each_output_drives_its_own_latent_modes():
    rates = spread_eigenvalues(6, 1.0, 10.0)
    a, b = latent_matrices(rates, n_y=2)
    np.testing.assert_array_equal(b, [[1, 0], [0, 1]] * 3)
    y = np.zeros((1, 50, 2))
    y[..., 1] = 1.0  # only the second output is on
    z = LatentObserver(a, b, 0.05).run(y)[0, -1]
    assert np.all(z[0::2] == 0.0)
    np.testing.assert_allclose(z[1::2], 1.0 / rates[1::2], rtol=0.2)  # near the steady state


@pytest.mark.parametrize("estimator", ["ekf", "ukf"])
@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=() if name in KIT_IN_THE_DEFAULT_RUN else pytest.mark.exhaustive)
        for name in NEW_SYSTEMS
        if name not in LARGE
    ],
)
def test_filters_pass_the_conformance_kit(estimator, name):
    check_estimator(estimator, name)


@pytest.mark.parametrize("estimator", ["autonomous_kkl", "gru_observer"])
def test_learned_estimators_pass_the_conformance_kit_with_several_outputs(estimator):
    """Lorenz-96 measures three of its five states: the latent design, the training data and
    every network see several outputs. Phase 1, which every KKL estimator builds on, and the
    recurrent baseline; each KKL estimator's own phase on several outputs runs in the
    more-systems track (about a minute each here, too long for every test run)."""
    check_estimator(estimator, "lorenz96-n5", few_steps(estimator))


@pytest.mark.parametrize("name", ["duffing", "vdp", "rossler", "lorenz", "fitzhugh_nagumo", "chua"])
def test_every_built_in_system_passes_the_system_checks(name):
    check_system(name)


def test_the_system_checks_name_a_wrong_jacobian_and_a_numpy_only_drift():
    class Wrong(systems.get("vdp")):
        def f_jacobian(self, x):
            jacobian = super().f_jacobian(x)
            jacobian[..., 1, 1] += 0.1
            return jacobian

        def f(self, x):
            return np.stack([x[..., 1], np.sin(x[..., 0])], axis=-1)

    failures = dict(run_system_checks(Wrong()))
    assert "f_jacobian differs from finite differences" in str(failures["check_f_jacobian"])
    assert "f fails on a torch tensor" in str(failures["check_evaluates_torch_tensors"])
    assert failures["check_h_jacobian"] is None and failures["check_shapes"] is None


def test_the_system_checks_name_a_compiled_model_that_is_not_the_systems():
    vdp, duffing = systems.get("vdp"), systems.get("duffing")().compiled()

    @numba.njit
    def returning(x, p, out):  # returns its output: not of the type the kernels take
        out[:] = x
        return out

    class Returning(vdp):
        def compiled(self):
            return replace(super().compiled(), drift=returning)

    class Another(vdp):
        def compiled(self):
            return replace(super().compiled(), drift=duffing.drift, p=duffing.p)

    failure = dict(run_system_checks(Returning()))["check_compiled_model"]
    assert "compiled().drift does not compile as" in str(failure)
    failure = dict(run_system_checks(Another()))["check_compiled_model"]
    assert "compiled().drift differs from the system's" in str(failure)
