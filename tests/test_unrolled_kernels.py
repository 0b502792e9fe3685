"""The unrolled EKF and UKF (``estimators/filters/kalman_unrolled.py``) against the generic kernels.

An unrolled kernel performs the generic kernel's operations in the generic kernel's
order, so the two agree bit for bit, NaN where a trajectory stopped included. Two cases
(each compiles a generic kernel, about half a minute) cover what the engine tests
(``tests/test_filter_engines.py``, the unrolled kernels against filterpy on every quick
paper and hard cell) do not reach: every update path at once (inflation, Huber's
noise, a sensor) with missing samples and a batch that is not a multiple of the lanes.
"""

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from kkl_bench.estimators.filters import kalman_kernels, kalman_unrolled

from kkl_bench.measurement import Quantized, Saturating, SensedSystem
from kkl_bench.protocol.scalar_source import Program, UntraceableError, scalars
from kkl_bench.registry import systems

DT = 0.05


def _model(system: str, sensor=None):
    plant = systems.get(system)()
    return (plant if sensor is None else SensedSystem(plant, sensor)).compiled()


def _streams(n_x: int, batch: int = 6, steps: int = 120):
    """Measurements with every fifth sample missing, one trajectory's from sample 40 on
    (a batch that is not a multiple of the kernels' lanes)."""
    rng = np.random.default_rng(3)
    y = rng.normal(size=(batch, steps, 1))
    y[:, ::5] = np.nan
    y[1, 40:] = np.nan
    u = 0.3 * rng.normal(size=(batch, steps))
    prior = (0.1 * np.ones(n_x), np.eye(n_x), 1e-3 * np.eye(n_x), np.array([[0.05]]))
    return y, u, prior


def _ekf_both(model, settings):
    y, u, (x0, P0, Q, R) = _streams(model.n_x)
    generic, unrolled = (np.full((*y.shape[:2], model.n_x), np.nan) for _ in range(2))
    kalman_kernels.ekf(
        *model.functions, model.p, model.q, model.s, model.g, y, u, DT, x0, P0, Q, R,
        *settings, generic,
    )  # fmt: skip
    kalman_unrolled.run_ekf(model, y, u, DT, x0, P0, Q, R, *settings, unrolled)
    return generic, unrolled


def _ukf_both(model, settings):
    y, u, (x0, P0, Q, R) = _streams(model.n_x)
    points = MerweScaledSigmaPoints(model.n_x, alpha=0.5, beta=2.0, kappa=0.0)
    spread = points.alpha**2 * (model.n_x + points.kappa)
    weights = (points.Wm, points.Wc, spread)
    generic, unrolled = (np.full((*y.shape[:2], model.n_x), np.nan) for _ in range(2))
    kalman_kernels.ukf(
        *model.functions, model.p, model.q, model.s, model.g, y, u, DT, x0, P0, Q, R,
        *weights, *settings, generic,
    )  # fmt: skip
    kalman_unrolled.run_ukf(model, y, u, DT, x0, P0, Q, R, *weights, *settings, unrolled)
    return generic, unrolled


@pytest.mark.slow
@pytest.mark.parametrize(
    ("run", "system", "sensor", "settings"),
    [
        (_ekf_both, "duffing", Quantized(step=0.1), (1.02, 1.5)),  # inflated, Huber
        (_ukf_both, "rossler", Saturating(limit=5.0), (1.02, 1.5)),  # and the constraint
    ],
    ids=["ekf-duffing-quantized", "ukf-rossler-saturating"],
)
def test_unrolled_kernel_is_bit_identical_to_the_generic_one(run, system, sensor, settings):
    generic, unrolled = run(_model(system, sensor), settings)
    assert np.isfinite(generic[0]).all()  # not a comparison of NaNs
    np.testing.assert_array_equal(unrolled, generic)


def test_which_models_are_unrolled():
    assert kalman_unrolled.unrollable(_model("duffing"))
    assert kalman_unrolled.unrollable(_model("lorenz", Quantized(step=0.1)))
    assert not kalman_unrolled.unrollable(_model("chua"))  # branches on the state
    assert not kalman_unrolled.unrollable(_model("lorenz96-n5"))  # over MAX_STATES
    assert not kalman_unrolled.unrollable(None)  # a plugin's system


def test_tracing_records_each_operation_in_order_constants_included():
    program = Program()
    x = scalars(program, "x", (2,))
    value = (0.0 + x[0] * 2.0) - -x[1] / np.float64(4.0)
    assert value.name == "v4"
    assert program.lines == [
        "v0 = x_0 * 2.0",
        "v1 = 0.0 + v0",
        "v2 = -x_1",
        "v3 = v2 / 4.0",
        "v4 = v1 - v3",
    ]
    assert np.tanh(value).name == "v5" and program.lines[-1] == "v5 = np.tanh(v4)"
    with pytest.raises(UntraceableError, match="branch"):
        bool(x[0] < 1.0)
