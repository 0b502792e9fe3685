"""Calibrating the nominal model on a true plant's logged data (the filters' +logged rows)."""

from __future__ import annotations

import dataclasses

import pytest

from kkl_bench.fitting.calibration import calibrate, calibrated_context
from kkl_bench.protocol import SIGMA_V, SIGMA_W
from kkl_bench.registry import systems
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.plants import logged_data, true_plant
from kkl_bench.suite.task import get_profile
from kkl_bench.suite.tracks import get_track


def fitted_and_true(system: str, plant: str):
    declared = get_track("mismatch").task(f"{plant}-sinusoid").plant
    logged = logged_data(system, declared, "mismatch", SIGMA_W, SIGMA_V)
    fitted = calibrate(systems.get(system)(), logged, SIGMA_W, SIGMA_V)
    truth = true_plant(system, declared, "mismatch").params()
    return fitted, truth, declared


@pytest.mark.parametrize(("system", "plant"), [("lorenz", "params25"), ("vdp", "params10")])
def test_the_physical_parameters_of_a_wrong_model_are_recovered(system, plant):
    fitted, truth, _ = fitted_and_true(system, plant)
    for name, value in truth.items():
        assert fitted.model.params()[name] == pytest.approx(value, rel=0.005), name
    assert fitted.gain == pytest.approx(1.0, abs=1e-3)
    assert fitted.offset == pytest.approx(0.0, abs=1e-3)


def test_the_sensor_gain_and_offset_are_recovered_and_the_model_kept():
    fitted, truth, declared = fitted_and_true("duffing", "sensor")
    assert fitted.gain == pytest.approx(declared.sensor_gain, abs=1e-3)
    assert fitted.offset == pytest.approx(declared.sensor_offset, abs=1e-3)
    assert fitted.model.params()["a"] == pytest.approx(truth["a"], rel=0.005)


def test_rosslers_reflected_steps_do_not_bias_its_constant_term():
    # without leaving out the components near the reflection, b came out 0.141 for 0.09
    fitted, truth, _ = fitted_and_true("rossler", "params10")
    assert fitted.model.params()["b"] == pytest.approx(truth["b"], rel=0.05)


def test_filters_fit_on_the_calibrated_model_only_when_given_logged_data():
    spec = RunSpec(("ekf",), ("vdp",), None, get_profile("quick"))
    nominal = make_fit_context(spec, "ekf", "vdp", 0)
    assert calibrated_context(nominal) is nominal
    declared = get_track("mismatch").task("params25-sinusoid").plant
    logged = dataclasses.replace(
        nominal, logged_data=logged_data("vdp", declared, "mismatch", SIGMA_W, SIGMA_V)
    )
    from kkl_bench import variants

    report = variants.build("ekf").fit(logged).fit_report()
    assert report["calibration"]["mu"] == pytest.approx(3.75, rel=0.005)
    assert "calibration" not in variants.build("ekf").fit(nominal).fit_report()


def test_kkl_observers_train_on_the_calibrated_model_given_logged_data(tmp_path):
    spec = RunSpec(("autonomous_kkl",), ("vdp",), None, get_profile("quick"), cache_dir=tmp_path)
    nominal = make_fit_context(spec, "autonomous_kkl", "vdp", 0)
    declared = get_track("mismatch").task("params25-sinusoid").plant
    logged = dataclasses.replace(
        nominal, logged_data=logged_data("vdp", declared, "mismatch", SIGMA_W, SIGMA_V)
    )
    from kkl_bench import variants

    fitted = variants.build("autonomous_kkl").fit(logged)
    context = fitted.check_fitted()
    assert fitted.fit_report()["calibration"]["mu"] == pytest.approx(3.75, rel=0.005)
    assert context.training.system is context.system  # training data from the calibrated model
    assert "calibration" not in variants.build("autonomous_kkl").fit(nominal).fit_report()


def test_a_training_generator_for_another_system_of_the_same_name_draws_the_same_streams():
    spec = RunSpec(("ekf",), ("vdp",), None, get_profile("quick"))
    training = make_fit_context(spec, "ekf", "vdp", 0).training
    from kkl_bench.registry import regimes

    family = regimes.get("sinusoid")()
    same = training.with_system(systems.get("vdp")()).simulate(family, 2, n_samples=20)
    original = training.simulate(family, 2, n_samples=20)
    assert (same.x == original.x).all() and (same.u == original.u).all()
    other = training.with_system(systems.get("vdp")(mu=1.5)).simulate(family, 2, n_samples=20)
    assert (other.u == original.u).all() and (other.x[:, 0] == original.x[:, 0]).all()
    assert not (other.x[:, -1] == original.x[:, -1]).all()
