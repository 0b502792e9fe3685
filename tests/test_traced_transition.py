"""The traced RK4 transition equals the generic sweep bit for bit, on every built-in system."""

import numba
import numpy as np
import pytest
from kkl_bench.estimators.filters.traced_transition import transition

from kkl_bench.protocol.compiled import rk4_step
from kkl_bench.registry import systems


@numba.njit
def _swept(drift, p, g, x, u, dt, out):
    rk4_step(drift, p, g, x, u, dt, out, np.empty((5, *x.shape)))


@pytest.mark.parametrize("name", ["duffing", "vdp", "rossler", "lorenz", "chua", "fitzhugh_nagumo"])
def test_the_traced_transition_is_the_sweep_bit_for_bit(name):
    model = systems.get(name)().compiled()
    step = transition(model)
    assert step is not None
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(model.n_x, 24)), rng.normal(size=24)
    traced, swept = np.empty_like(x), np.empty_like(x)
    step(x, model.p, model.s, model.g, u, 0.01, traced)
    _swept(model.drift, model.p, model.g, x, u, 0.01, swept)
    assert np.array_equal(traced, swept)


def test_a_system_without_a_compiled_model_has_no_traced_transition():
    assert transition(None) is None
