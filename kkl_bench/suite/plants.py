"""True plants of the ``mismatch`` track and the data logged on them (protocol section 7.5).

On most tracks the plant that makes the data is the nominal model every
estimator is given. A :class:`~kkl_bench.suite.tracks.Plant` declares how it differs
instead: parameters off by a fixed relative error and a sensor with a gain
and an offset. This module builds that plant (:func:`true_plant`), simulates
its measurements (:func:`simulate_plant`), and draws the small set of trajectories
a user would have logged on the real machine (:func:`logged_data`).

The parameter errors are drawn from a stream of their own, sealed like the
test streams: an estimator that asks for them inside
:func:`~kkl_bench.protocol.streams.sealed_test_streams` fails the
conformance kit. Logged data are not sealed; they are what an estimator
that declares ``uses_logged_data`` receives, as ``FitContext.logged_data``.
"""

from __future__ import annotations

import functools

import numpy as np

from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol import DT, N_SAMPLES
from kkl_bench.protocol.simulate import Trajectories, simulate
from kkl_bench.protocol.streams import draw_trajectory, root_seed, trajectory_rng
from kkl_bench.protocol.system import System
from kkl_bench.registry import regimes, systems
from kkl_bench.suite.tracks import Plant

LOGGED_TRAJECTORIES = 100
"""Trajectories logged on each true plant: a quarter from each of the paper's regimes."""
LOGGED_FAMILIES = ("zero", "constant", "sinusoid", "square")


def parameter_factors(system: str, plant: Plant, track: str) -> dict[str, float]:
    """``{parameter: factor}``: each of ``system``'s parameters times ``1 +/- plant.parameters``,
    the sign drawn from the track's sealed plant stream. Empty for the nominal parameters."""
    params = systems.get(system)().params()
    if plant.parameters == 0.0 or not params:
        return {}
    rng = np.random.default_rng(root_seed(system, plant.key, "plant", track))
    signs = rng.choice((-1.0, 1.0), size=len(params))
    return {
        name: 1.0 + plant.parameters * float(sign) for name, sign in zip(params, signs, strict=True)
    }


def true_plant(system: str, plant: Plant, track: str) -> System:
    """The model of the plant that makes ``track``'s data for ``system``."""
    nominal = systems.get(system)()
    factors = parameter_factors(system, plant, track)
    if not factors:
        return nominal
    return type(nominal)(
        **{name: value * factors[name] for name, value in nominal.params().items()}
    )


def simulate_plant(
    model: System,
    plant: Plant,
    x0: np.ndarray,
    u: np.ndarray,
    process_noise: np.ndarray,
    measurement_noise: np.ndarray,
    measurement: MeasurementModel | None = None,
) -> Trajectories:
    """:func:`~kkl_bench.protocol.simulate.simulate` on the true plant ``model``, read by the
    plant's sensor: ``y = sensor_gain s(h(x)) + sensor_offset + v``, with the task's sensor
    ``s`` and sampling (default: ``s(h) = h``, every sample; shapes as ``simulate``)."""
    measurement = measurement or MeasurementModel()
    data = simulate(measurement.system(model), x0, u, DT, process_noise)
    output = data.y
    if plant.sensor_gain != 1.0 or plant.sensor_offset != 0.0:
        output = plant.sensor_gain * output + plant.sensor_offset
    return Trajectories(data.t, data.u, data.x, measurement.measure(output, measurement_noise))


@functools.lru_cache(maxsize=16)
def logged_data(
    system: str, plant: Plant, track: str, sigma_w: float, sigma_v: float
) -> Trajectories:
    """The trajectories logged on ``track``'s true plant for ``system``, with their states.

    :data:`LOGGED_TRAJECTORIES` trajectories of ``N_SAMPLES`` samples, the first
    quarter unforced, then constant, sinusoid and square inputs (the paper's
    regimes), from the paper's x0 box, with process and measurement noise of
    standard deviations ``sigma_w`` and ``sigma_v``; trajectory ``i`` draws from
    the track's ``logged`` stream exactly as a test trajectory does. The same
    for every run and seed (the arrays are read-only).
    """
    model = true_plant(system, plant, track)
    root = root_seed(system, plant.key, "logged", track)
    t = DT * np.arange(N_SAMPLES)
    per_family = LOGGED_TRAJECTORIES // len(LOGGED_FAMILIES)
    parts = []
    for number, family in enumerate(LOGGED_FAMILIES):
        regime = regimes.get(family)()
        draws = [
            draw_trajectory(
                trajectory_rng(root, number * per_family + i),
                model.x0_low,
                model.x0_high,
                N_SAMPLES,
                sigma_w,
                sigma_v,
                regime.n_numbers(t),
                model.n_y,
            )
            for i in range(per_family)
        ]
        u = regime.signal(t, regime.params_from_uniform(np.stack([d.r for d in draws])))
        parts.append(
            simulate_plant(
                model,
                plant,
                np.stack([d.x0 for d in draws]),
                u,
                np.stack([d.process_noise for d in draws]),
                np.stack([d.measurement_noise for d in draws]),
            )
        )
    logged = Trajectories(
        t, *(np.concatenate([getattr(p, name) for p in parts]) for name in ("u", "x", "y"))
    )
    for array in (logged.t, logged.u, logged.x, logged.y):
        array.flags.writeable = False
    return logged
