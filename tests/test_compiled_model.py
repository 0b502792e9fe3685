"""Every built-in system's compiled model computes what its numpy model computes."""

import numpy as np
import pytest

from kkl_bench.measurement import MeasurementModel, Quantized, Saturating
from kkl_bench.protocol import compiled
from kkl_bench.protocol.simulate import rk4_step, rk4_step_jacobian
from kkl_bench.registry import systems

DT = 0.05


def states(system, count=16, seed=0):
    """``(count, n_x)`` states from a box three times the x0 box."""
    rng = np.random.default_rng(seed)
    centre, half = (system.x0_high + system.x0_low) / 2, (system.x0_high - system.x0_low) * 1.5
    return centre + half * rng.uniform(-1, 1, (count, system.n_x))


@pytest.mark.parametrize("name", systems.names())
def test_compiled_drift_output_and_rk4_step_equal_the_numpy_model(name):
    system = systems.get(name)()
    model = system.compiled()
    assert model is not None, f"{name} has no compiled model"
    n, n_y = system.n_x, system.n_y
    assert model.n_y == n_y
    x = states(system)
    points = np.ascontiguousarray(x.T)  # the sweep: (n_x, m)
    m = points.shape[1]
    drift, jacobian = np.empty((n, m)), np.full((n, n, m), np.nan)
    model.drift(points, model.p, drift)
    model.drift_jacobian(points, model.p, jacobian)
    np.testing.assert_allclose(drift.T, system.f(x), rtol=1e-14, atol=1e-14)
    jacobian = np.moveaxis(jacobian, -1, 0)
    np.testing.assert_allclose(jacobian, system.f_jacobian(x), rtol=1e-14, atol=1e-14)
    assert max(np.count_nonzero(each) for each in jacobian) <= model.jacobian_nonzeros
    output, output_jacobian = np.empty((n_y, m)), np.full((n_y, n, m), np.nan)
    model.output(points, model.q, output)
    model.output_jacobian(points, model.q, output_jacobian)
    np.testing.assert_array_equal(output.T, system.h(x))
    np.testing.assert_array_equal(np.moveaxis(output_jacobian, -1, 0), system.h_jacobian(x))
    u = np.full(m, 0.7)
    step, step_jacobian = np.empty((n, m)), np.empty((n, n, m))
    compiled.rk4_step(model.drift, model.p, model.g, points, u, DT, step, np.empty((5, n, m)))
    compiled.rk4_step_jacobian(
        model.drift, model.drift_jacobian, model.p, model.g, points, u, DT,
        step_jacobian, np.empty((5, n, m)), np.empty((5, n, n, m)),
    )  # fmt: skip
    for j, point in enumerate(x):  # numpy's step, one point at a time
        np.testing.assert_allclose(
            step[:, j], rk4_step(system, point, np.array(0.7), DT), rtol=1e-14
        )
        np.testing.assert_allclose(
            step_jacobian[:, :, j],
            rk4_step_jacobian(system, point, np.array(0.7), DT),
            rtol=1e-13,
            atol=1e-15,
        )


@pytest.mark.parametrize("sensor", [Quantized(step=0.5), Saturating(limit=0.8)])
def test_a_sensed_system_compiles_its_sensor(sensor):
    system = MeasurementModel(sensor=sensor).system(systems.get("vdp")())
    model = system.compiled()
    x = states(system)
    points = np.ascontiguousarray(x.T)
    output, slope = np.empty((1, len(x))), np.empty((1, len(x)))
    model.output(points, model.q, output)
    model.sense_slope(output, model.s, slope)
    model.sense(output, model.s)
    np.testing.assert_allclose(output.T, system.h(x), rtol=1e-15)
    np.testing.assert_allclose(
        slope.T[:, :, None] * [[1.0, 0.0]], system.h_jacobian(x), rtol=1e-12, atol=1e-15
    )


def test_the_rossler_constraint_reflects_x3():
    model = systems.get("rossler")().compiled()
    x = np.array([[1.0, 2.0, -0.25], [3.0, -1.0, 0.5]]).T.copy()
    model.constrain(x, model.p)
    np.testing.assert_array_equal(x.T, [[1.0, 2.0, 0.25], [3.0, -1.0, 0.5]])


def test_a_calibrated_system_compiles_its_affine_sensor():
    from kkl_bench.fitting.calibration import CalibratedSystem

    system = CalibratedSystem(systems.get("lorenz")(p=11.0), gain=1.05, offset=0.02)
    model = system.compiled()
    np.testing.assert_array_equal(model.p, [11.0, 28.0, 8.0 / 3.0])
    x = states(system)
    output, slope = np.empty((1, len(x))), np.empty((1, len(x)))
    model.output(np.ascontiguousarray(x.T), model.q, output)
    model.sense_slope(output, model.s, slope)
    model.sense(output, model.s)
    np.testing.assert_array_equal(output.T, system.h(x))
    np.testing.assert_array_equal(slope.T[:, :, None] * [[0.0, 1.0, 0.0]], system.h_jacobian(x))
