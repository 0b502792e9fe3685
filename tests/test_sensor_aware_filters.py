"""The model-based filters built for the task's sensor (protocol 7.6): Huber's robust update,
a quantizer read as additive noise, the system's constraint in the propagation, and the
settings chosen on validation streams."""

import math

import numpy as np
import pytest
from kkl_bench.estimators.filters.kalman import INFLATIONS, THRESHOLDS, huber_noise

from kkl_bench import variants
from kkl_bench.measurement import MeasurementModel, Quantized, Saturating, filter_system
from kkl_bench.registry import systems
from kkl_bench.run.spec import RunSpec, fit_context_for_row
from kkl_bench.suite.task import get_profile, make_test_set


def spec(tmp_path, track):
    return RunSpec(
        estimators=("ekf", "ukf"),
        systems=("duffing", "vdp", "rossler", "lorenz"),
        regimes=None,
        tracks=(track,),
        profile=get_profile("quick"),
        seeds=(0,),
        results_dir=tmp_path,
        cache_dir=tmp_path,
    )


def task_named(run_spec, system, regime):
    return next(t for t in run_spec.tasks(system) if t.regime == regime)


def fitted(run_spec, row, task):
    context = fit_context_for_row(run_spec, row, task.system, [task], seed=0)
    return variants.build(row).fit(context)


def rmse(estimator, task):
    data = make_test_set(task, 5).data
    x_hat = estimator.estimate(data.t, data.y, data.u)
    return float(np.sqrt(np.mean((x_hat[:, 51:] - data.x[:, 51:]) ** 2)))


def test_huber_divides_each_outputs_variance_by_its_weight():
    R = np.diag([1.0, 2.0])
    S = np.diag([4.0, 2.0])
    residual = np.array([3.0, -0.5])  # 1.5 and 0.354 predicted standard deviations
    expected = np.diag([1.0 / (1.345 / 1.5), 2.0])
    np.testing.assert_allclose(huber_noise(R, residual, S, 1.345), expected)
    assert huber_noise(R, residual, S, math.inf) is R  # the plain update
    np.testing.assert_array_equal(huber_noise(R, np.zeros(2), S, 1.0), R)


def test_a_quantizer_is_left_out_of_the_filters_model_and_other_sensors_are_kept():
    duffing = systems.get("duffing")()
    quantized = MeasurementModel(sensor=Quantized(step=0.5))
    saturating = MeasurementModel(sensor=Saturating(limit=1.0))
    assert filter_system(quantized.system(duffing), quantized) is duffing
    sensed = saturating.system(duffing)
    assert filter_system(sensed, saturating) is sensed
    assert quantized.variance == pytest.approx(0.01**2 + 0.5**2 / 12)


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_on_the_paper_track_the_filter_is_the_plain_one(name, tmp_path):
    run_spec = spec(tmp_path, "paper")
    estimator = fitted(run_spec, name, task_named(run_spec, "duffing", "sinusoid"))
    report = estimator.fit_report()
    assert (report["update"], report["inflation"], report["noise_variance"]) == (
        "gaussian",
        1.0,
        pytest.approx(1e-4),
    )
    assert "selection" not in report


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_under_outliers_the_update_is_hubers_with_settings_chosen_on_validation(name, tmp_path):
    run_spec = spec(tmp_path, "hard")
    task = task_named(run_spec, "duffing", "outliers-sinusoid")
    robust = fitted(run_spec, name, task)
    report = robust.fit_report()
    assert report["update"] == "huber" and report["huber_threshold"] in THRESHOLDS
    assert report["noise_variance"] == pytest.approx(0.05**2)  # the inliers' variance
    assert len(report["selection"]) == len(THRESHOLDS) * len(INFLATIONS)
    chosen = f"threshold={report['huber_threshold']:g},inflation={report['inflation']:g}"
    assert report["selection"][chosen] == min(report["selection"].values())
    huber = fitted(run_spec, f"{name}[inflation=1.0,threshold=1.345]", task)
    plain = fitted(run_spec, f"{name}[inflation=1.0,robust='none']", task)
    assert rmse(huber, task) < 0.6 * rmse(plain, task)


def test_the_ukf_reading_the_quantizer_as_noise_beats_the_one_with_it_inside(tmp_path):
    run_spec = spec(tmp_path, "hard")
    task = task_named(run_spec, "vdp", "quantized-sinusoid")
    as_noise = fitted(run_spec, "ukf[inflation=1.0,quantizer='noise']", task)
    inside = fitted(run_spec, "ukf[inflation=1.0,quantizer='in-model']", task)
    assert as_noise.fit_report()["quantizer"] == "noise"
    assert rmse(as_noise, task) < 0.5 * rmse(inside, task)


@pytest.mark.parametrize("name", ["ekf", "enkf[inflation=1.0]"])
def test_by_default_the_quantizers_treatment_is_chosen_on_validation(name, tmp_path):
    run_spec = spec(tmp_path, "hard")
    estimator = fitted(run_spec, name, task_named(run_spec, "duffing", "quantized-square"))
    report = estimator.fit_report()
    scores = report["selection"]
    assert {key.split(",")[0] for key in scores} == {"quantizer=noise", "quantizer=in-model"}
    best = min(scores, key=scores.get)
    assert best.startswith(f"quantizer={report['quantizer']},")


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_the_propagation_applies_the_systems_constraint(name, tmp_path):
    """Rossler's x3 is reflected at 0 after the RK4 step (erratum E1), as in the plant."""
    run_spec = spec(tmp_path, "paper")
    estimator = fitted(run_spec, name, task_named(run_spec, "rossler", "zero"))
    kalman_filter = estimator.make_filter(estimator.settings_, 0.05)
    state = np.array([20.0, 0.0, -0.5])  # x1 > c: a negative x3 would run away
    if name == "ekf":
        kalman_filter.x = state[:, None].copy()
    else:
        kalman_filter.x = state.copy()
    kalman_filter.predict(0.0)
    assert np.ravel(kalman_filter.x)[2] >= 0.0


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("ekf[robust='tukey']", r"robust='tukey'; valid: auto, huber, none"),
        ("ukf[quantizer='dither']", r"quantizer='dither'; valid: auto, noise, in-model"),
        ("enkf[quantizer='dither']", r"quantizer='dither'; valid: auto, noise, in-model"),
        ("ekf[threshold=-1]", r"threshold=-1 must be a positive number, or None"),
        ("ukf[inflation=0.5]", r"inflation=0.5 must be a number of at least 1, or None"),
    ],
)
def test_a_bad_design_is_refused_with_the_valid_choices(row, message):
    with pytest.raises(ValueError, match=message):
        variants.build(row)
