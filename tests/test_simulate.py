"""RK4 against a tight scipy solve_ivp, the RK4 Jacobian, and the simulator's noise handling."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from kkl_bench.protocol.simulate import rk4_step, rk4_step_jacobian, simulate
from kkl_bench.registry import regimes, systems

SYSTEM_NAMES = [
    "duffing",
    "vdp",
    "rossler",
    "lorenz",
    "fitzhugh_nagumo",
    "chua",
    "lorenz96-n5",
    "lorenz96-n10",
]
NONSMOOTH = {"chua"}
"""Systems whose vector field has kinks (Chua's diode at |x| = 1): RK4 is only second order
across them."""


def held_input_reference(system, x0, u, dt):
    """solve_ivp (DOP853, rtol = atol = 1e-12) interval by interval with u held: (steps, n_x)."""
    states = [np.asarray(x0, dtype=float)]
    for k in range(len(u) - 1):
        solution = solve_ivp(
            lambda _, x, uk=u[k]: system.vector_field(x, np.asarray(uk)),
            (0.0, dt),
            states[-1],
            method="DOP853",
            rtol=1e-12,
            atol=1e-12,
        )
        states.append(solution.y[:, -1])
    return np.array(states)


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_rk4_matches_solve_ivp_with_fourth_order_convergence(name):
    system = systems.get(name)()
    rng = np.random.default_rng(1)
    x0 = rng.uniform(system.x0_low, system.x0_high)
    horizon = 1.0
    errors = []
    for dt in (0.01, 0.005):
        t = dt * np.arange(round(horizon / dt) + 1)
        u = np.sin(1.3 * t)
        x = simulate(system, x0[None], u[None], dt).x[0]
        errors.append(np.abs(x - held_input_reference(system, x0, u, dt)).max())
    assert errors[1] < 1e-5 * max(1.0, np.abs(x).max())
    # halving the step divides the global error by about 2^4 = 16 (2^2 = 4 across kinks)
    low = 3 if name in NONSMOOTH else 10
    assert low < errors[0] / errors[1] < 24


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_rk4_jacobian_matches_finite_differences(name):
    system = systems.get(name)()
    rng = np.random.default_rng(2)
    x = rng.uniform(system.x0_low, system.x0_high, (4, system.n_x))
    u = rng.uniform(-1, 1, 4)
    jacobian = rk4_step_jacobian(system, x, u, 0.05)
    eps = 1e-6
    for j in range(system.n_x):
        step = np.zeros(system.n_x)
        step[j] = eps
        column = (rk4_step(system, x + step, u, 0.05) - rk4_step(system, x - step, u, 0.05)) / (
            2 * eps
        )
        np.testing.assert_allclose(jacobian[..., j], column, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_f_jacobian_matches_finite_differences(name):
    system = systems.get(name)()
    x = np.random.default_rng(3).uniform(-2, 2, (5, system.n_x))
    eps = 1e-6
    for j in range(system.n_x):
        step = np.zeros(system.n_x)
        step[j] = eps
        column = (system.f(x + step) - system.f(x - step)) / (2 * eps)
        np.testing.assert_allclose(system.f_jacobian(x)[..., j], column, rtol=1e-6, atol=1e-6)


def test_noise_enters_as_the_protocol_says():
    system = systems.get("duffing")()
    x0 = np.array([[0.5, -0.2]])
    u = np.full((1, 4), 0.3)
    w = np.full((1, 3, 2), 0.01)
    v = np.full((1, 4, 1), -0.02)
    noisy = simulate(system, x0, u, 0.05, w, v)
    x1 = rk4_step(system, x0[0], np.array(0.3), 0.05) + 0.01
    np.testing.assert_allclose(noisy.x[0, 1], x1)
    np.testing.assert_allclose(noisy.y[0, :, 0], noisy.x[0, :, 0] - 0.02)
    assert noisy.u.shape == (1, 4, 1)


def test_rossler_reflects_x3_at_zero_after_noise():
    """Erratum E1: x3 >= 0 holds even when the noise pushes it below 0."""
    system = systems.get("rossler")()
    x0 = np.array([[1.0, 1.0, 0.001]])
    w = np.zeros((1, 1, 3))
    w[0, 0, 2] = -1.0
    x = simulate(system, x0, np.zeros((1, 2)), 0.05, w).x
    assert x[0, 1, 2] > 0
    np.testing.assert_allclose(x[0, 1, 2], -(rk4_step(system, x0[0], np.array(0.0), 0.05)[2] - 1.0))


def test_simulate_rejects_mismatched_shapes():
    system = systems.get("lorenz")()
    with pytest.raises(ValueError, match=r"x0 has shape \(2, 2\); expected \(2, 3\)"):
        simulate(system, np.zeros((2, 2)), np.zeros((2, 10)), 0.05)


@pytest.mark.parametrize("name", ["zero", "constant", "sinusoid", "square"])
def test_regime_signals_stay_within_their_amplitude(name):
    regime = regimes.get(name)()
    r = np.random.default_rng(4).random((50, 3))
    params = regime.params_from_uniform(r)
    u = regime.signal(0.05 * np.arange(1001), params)
    assert u.shape == (50, 1001)
    assert np.abs(u).max() <= 1.0
