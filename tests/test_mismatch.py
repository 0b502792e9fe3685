"""The mismatch track: true plants, their sealed parameter errors, logged data, and the
second fit with logged data the harness runs for estimators that declare they use it."""

from typing import ClassVar

import numpy as np
import pytest

from kkl_bench import variants
from kkl_bench.estimator import Estimator
from kkl_bench.protocol import N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.protocol.streams import TestStreamAccessError, sealed_test_streams
from kkl_bench.registry import systems
from kkl_bench.run.harness import RunSpec, plan, run
from kkl_bench.run.results import read_cell
from kkl_bench.suite.plants import LOGGED_TRAJECTORIES, logged_data, parameter_factors, true_plant
from kkl_bench.suite.task import Task, build_test_set, get_profile
from kkl_bench.suite.tracks import Plant, TrackError, get_track, parse_track

TRACK = get_track("mismatch")
PARAMS25 = TRACK.task("params25-sinusoid").plant
SENSOR = TRACK.task("sensor-sinusoid").plant


def test_the_track_declares_two_parameter_levels_and_a_sensor_error():
    plants = {TRACK.task(name).plant for name in TRACK.task_names()}
    assert plants == {Plant(parameters=0.1), Plant(parameters=0.25), SENSOR}
    assert Plant(sensor_gain=1.05, sensor_offset=0.02) == SENSOR
    assert all(not plant.nominal for plant in plants)
    assert all(task.plant.nominal for task in get_track("paper").tasks)


@pytest.mark.parametrize("system", TRACK.systems)
def test_every_parameter_is_off_by_exactly_the_level(system):
    factors = parameter_factors(system, PARAMS25, "mismatch")
    nominal = systems.get(system)().params()
    assert set(factors) == set(nominal) and nominal
    assert all(abs(abs(factor - 1.0) - 0.25) < 1e-12 for factor in factors.values())
    plant = true_plant(system, PARAMS25, "mismatch")
    assert plant.params() == pytest.approx({k: v * factors[k] for k, v in nominal.items()})
    assert parameter_factors(system, PARAMS25, "mismatch") == factors  # pinned, not random
    assert true_plant(system, SENSOR, "mismatch").params() == nominal


def test_the_true_plants_are_sealed_like_the_test_streams():
    with sealed_test_streams(), pytest.raises(TestStreamAccessError, match="plant stream"):
        true_plant("vdp", PARAMS25, "mismatch")


def test_a_sensor_task_measures_gain_times_h_plus_offset():
    data = build_test_set(Task("vdp", "sensor-sinusoid", 1, "mismatch"), 3).data
    residual = data.y[..., 0] - (1.05 * data.x[..., 0] + 0.02)
    assert abs(residual.mean()) < 2e-3 and residual.std() == pytest.approx(SIGMA_V, rel=0.1)


def test_a_parameter_task_is_simulated_on_the_true_plant():
    """Same draws as the nominal cell of the same family would use under this track's key,
    different states: the plant's mu is 3 * (1 +/- 0.25)."""
    mismatch = build_test_set(Task("vdp", "params25-sinusoid", 1, "mismatch"), 2).data
    mu = true_plant("vdp", PARAMS25, "mismatch").mu
    assert mu in (pytest.approx(2.25), pytest.approx(3.75))
    x, u = mismatch.x, mismatch.u[..., 0]
    # the true plant's RK4 step reproduces the stored states up to the process noise
    step = rk4_step(true_plant("vdp", PARAMS25, "mismatch"), x[:, :-1], u[:, :-1], 0.05)
    assert np.std(x[:, 1:] - step) == pytest.approx(SIGMA_W, rel=0.1)
    nominal_step = rk4_step(systems.get("vdp")(), x[:, :-1], u[:, :-1], 0.05)
    assert np.std(x[:, 1:] - nominal_step) > 3 * SIGMA_W


def test_logged_data_come_from_the_true_plant_and_are_fixed():
    logged = logged_data("vdp", SENSOR, "mismatch", SIGMA_W, SIGMA_V)
    assert logged.x.shape == (LOGGED_TRAJECTORIES, N_SAMPLES, 2)
    assert logged.y.shape == (LOGGED_TRAJECTORIES, N_SAMPLES, 1)
    assert not logged.x.flags.writeable
    residual = logged.y[..., 0] - (1.05 * logged.x[..., 0] + 0.02)
    assert residual.std() == pytest.approx(SIGMA_V, rel=0.05)
    # a quarter of them unforced, the rest forced
    unforced = np.all(logged.u == 0.0, axis=(1, 2))
    assert unforced.sum() == LOGGED_TRAJECTORIES // 4 and unforced[: LOGGED_TRAJECTORIES // 4].all()
    logged_data.cache_clear()
    again = logged_data("vdp", SENSOR, "mismatch", SIGMA_W, SIGMA_V)
    assert again.fingerprint() == logged.fingerprint()


@pytest.mark.parametrize(
    ("plant", "message"),
    [
        ("{gain = 1.05}", "unknown field 'plant.gain'; valid: parameters, sensor_gain"),
        ("{parameters = 1.5}", "'plant.parameters' must be below 1"),
        ("{sensor_gain = 0.0}", "'plant.sensor_gain' must not be 0"),
        ("{parameters = -0.1}", "'plant.parameters' must be non-negative"),
    ],
)
def test_bad_plants_are_named(plant, message):
    text = f"""
name = "bad"
version = 1
systems = ["vdp"]
[[task]]
name = "t"
family = "sinusoid"
plant = {plant}
"""
    with pytest.raises(TrackError, match=message.replace("(", r"\(")):
        parse_track(text, "bad.toml")


class _RecordsLoggedData(Estimator):
    """Estimates zeros; remembers what ``fit`` received."""

    name = "records_logged_data"
    uses_logged_data = True
    seen: ClassVar[list] = []

    def fit(self, context):
        type(self).seen.append(None if context.logged_data is None else context.logged_data)
        return super().fit(context)

    def estimate(self, t, y, u):
        return np.zeros((*y.shape[:2], self.check_fitted().system.n_x))


def test_an_estimator_using_logged_data_gets_one_more_row_fitted_per_plant(
    tmp_path, register_estimator
):
    register_estimator("records_logged_data", _RecordsLoggedData)
    register_estimator("plain", type("Plain", (_RecordsLoggedData,), {"uses_logged_data": False}))
    spec = RunSpec(
        ("records_logged_data", "plain"),
        ("vdp",),
        None,
        get_profile("quick"),
        results_dir=tmp_path / "results",
        cache_dir=tmp_path / "cache",
        tracks=("paper", "mismatch"),
    )
    jobs, _ = plan(spec)
    rows = [(job.estimator, tuple(task.regime for task in job.tasks)) for job in jobs]
    assert rows == [
        ("records_logged_data", tuple(get_track("paper").task_names() + TRACK.task_names())),
        ("records_logged_data+logged", ("params10-sinusoid", "params10-square")),
        ("records_logged_data+logged", ("params25-sinusoid", "params25-square")),
        ("records_logged_data+logged", ("sensor-sinusoid", "sensor-square")),
        ("plain", tuple(get_track("paper").task_names() + TRACK.task_names())),
    ]
    _RecordsLoggedData.seen = []
    summary = run(spec)
    assert summary.ok
    seen = _RecordsLoggedData.seen
    assert sum(logged is None for logged in seen) == 2  # the usual fits
    fingerprints = {logged.fingerprint() for logged in seen if logged is not None}
    assert len(fingerprints) == 3  # one logged set per true plant
    cell = read_cell(
        tmp_path / "results/quick/records_logged_data+logged/vdp/mismatch/sensor-square-seed0.json"
    )
    assert cell.status == "ok" and cell.estimator == "records_logged_data+logged"
    assert variants.base_name(cell.estimator) == "records_logged_data"


def test_own_rows_only_fits_no_logged_row_and_refuses_to_be_given_one(tmp_path, register_estimator):
    register_estimator("records_logged_data", _RecordsLoggedData)
    arguments = ("vdp",), None, get_profile("quick")
    spec = RunSpec(
        ("records_logged_data",), *arguments, results_dir=tmp_path, cache_dir=tmp_path,
        tracks=("mismatch",), own_rows_only=True,
    )  # fmt: skip
    jobs, _ = plan(spec)
    assert [(job.estimator, len(job.tasks)) for job in jobs] == [("records_logged_data", 6)]
    with pytest.raises(
        ValueError, match="'records_logged_data\\+logged' is not an estimator's own row"
    ):
        RunSpec(
            ("records_logged_data+logged",), *arguments, tracks=("mismatch",), own_rows_only=True
        )
