"""Measurement models owned by the task: sensors, sampling and noise laws (protocol 7.6)."""

import dataclasses

import numpy as np
import pytest
import torch
from kkl_bench.estimators.learned.kalmannet import KalmanNetFilter
from scipy import integrate

from kkl_bench import registry, variants
from kkl_bench.estimator import Estimator
from kkl_bench.kkl.latent import LatentObserver, latent_matrices
from kkl_bench.kkl.sequence import inputs
from kkl_bench.measurement import MeasurementModel, NoiseLaw, Quantized, Saturating, held
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.run.harness import RunSpec, rows_and_tasks, run
from kkl_bench.run.results import load_results
from kkl_bench.run.spec import PROTOCOL_CONDITIONS, conditioned_context, fit_context_for_row
from kkl_bench.suite.task import Task, build_test_set, get_profile
from kkl_bench.suite.tracks import TRACKS_ENV, TrackError, load_tracks, parse_track

TRACK = """
name = "sensing"
version = 1
systems = ["duffing", "lorenz"]
fitted_per_task = true

[[task]]
name = "all-three"
family = "sinusoid"
measurement_noise = {default = 0.2, lorenz = 2.0}
measurement = {sensor = "quantized", step = {default = 0.5, lorenz = 5.0}, observe_every = 4, noise = "student-t", dof = 3}

[[task]]
name = "plain"
family = "sinusoid"
"""


@pytest.fixture
def sensing_track(tmp_path, monkeypatch):
    (tmp_path / "sensing.toml").write_text(TRACK)
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    return load_tracks()["sensing"]


def test_saturating_sensor_and_its_slope():
    sensor = Saturating(limit=2.0)
    h = np.linspace(-5, 5, 11)
    assert np.allclose(sensor(h), 2.0 * np.tanh(h / 2.0))
    step = 1e-6
    numeric = (sensor(h + step) - sensor(h - step)) / (2 * step)
    assert np.allclose(sensor.slope(h), numeric, atol=1e-8)


def test_quantized_sensor_rounds_to_its_step_and_adds_the_uniform_variance():
    sensor = Quantized(step=0.5)
    assert sensor(np.array([0.2, 0.26, -0.74, 1.0])).tolist() == [0.0, 0.5, -0.5, 1.0]
    assert sensor.added_variance == pytest.approx(0.25 / 12)
    with pytest.raises(ValueError, match="step=0"):
        Quantized(step=0)


@pytest.mark.parametrize(
    "law",
    [
        NoiseLaw("gaussian", 0.3),
        NoiseLaw("student-t", 0.3, dof=3.0),
        NoiseLaw("outliers", 0.3, outlier_fraction=0.1, outlier_scale=20.0),
    ],
    ids=lambda law: law.law,
)
def test_noise_laws_densities_integrate_to_one_and_samples_have_their_variance(law):
    density = lambda v: np.exp(law.log_density(np.array([[v]]))[0])  # noqa: E731
    mass = sum(
        integrate.quad(density, a, b, limit=200)[0] for a, b in [(-60, -1), (-1, 1), (1, 60)]
    )
    assert mass == pytest.approx(1.0, abs=2e-3)  # Student-t with 3 dof: tails past 60 sigma
    samples = law.sample(np.random.default_rng(0), (400_000, 1))
    assert np.var(samples) == pytest.approx(law.variance, rel=0.05)


def test_gaussian_noise_is_the_protocols_draw():
    law = NoiseLaw("gaussian", 0.01)
    drawn = law.sample(np.random.default_rng(5), (7, 1))
    assert np.array_equal(drawn, 0.01 * np.random.default_rng(5).standard_normal((7, 1)))


def test_bad_measurement_fields_are_named_with_the_valid_choices():
    base = 'name = "t"\nversion = 1\nsystems = ["duffing"]\n[[task]]\nname = "a"\nfamily = "zero"\n'
    with pytest.raises(TrackError, match="unknown sensor 'lidar'; valid sensors: identity"):
        parse_track(base + 'measurement = {sensor = "lidar"}')
    with pytest.raises(TrackError, match="unknown law 'cauchy'; valid laws: gaussian"):
        parse_track(base + 'measurement = {noise = "cauchy"}')
    with pytest.raises(TrackError, match="observe_every' must be a positive integer, got 0"):
        parse_track(base + "measurement = {observe_every = 0}")
    with pytest.raises(TrackError, match=r"'measurement\.limit'.*sensor 'quantized' takes step"):
        parse_track(base + 'measurement = {sensor = "quantized", limit = 1.0}')
    with pytest.raises(TrackError, match="set for 'chua', not a system of this track"):
        parse_track(base + "measurement_noise = {default = 0.1, chua = 1.0}")


def test_a_measurement_model_round_trips_through_track_test_set_and_fit_context(sensing_track):
    duffing, lorenz = (Task(s, "all-three", 1, "sensing") for s in ("duffing", "lorenz"))
    measurement = duffing.definition.measurement
    assert measurement == MeasurementModel(Quantized(0.5), 4, NoiseLaw("student-t", 0.2, dof=3.0))
    assert lorenz.definition.measurement.sensor == Quantized(5.0)
    assert lorenz.definition.sigma_v == 2.0

    test_set = build_test_set(duffing, 3)
    y = test_set.data.y
    observed = np.arange(y.shape[1]) % 4 == 0
    assert np.isfinite(y[:, observed]).all() and np.isnan(y[:, ~observed]).all()
    # present samples: the quantized output plus heavy-tailed noise
    residual = y[:, observed, 0] - 0.5 * np.round(test_set.data.x[:, observed, 0] / 0.5)
    assert np.max(np.abs(residual)) > 5 * 0.2  # Student-t tails
    plain = build_test_set(Task("duffing", "plain", 1, "sensing"), 3)
    assert test_set.stream_fingerprint != plain.stream_fingerprint
    assert build_test_set(duffing, 3).fingerprint == test_set.fingerprint

    spec = RunSpec(("ukf",), ("duffing",), None, get_profile("quick"), tracks=("sensing",))
    (_, sensing_tasks), (_, plain_tasks) = rows_and_tasks(spec, "ukf", "duffing")
    assert [t.regime for t in sensing_tasks] == ["all-three"]
    context = fit_context_for_row(spec, "ukf", "duffing", sensing_tasks, 0)
    assert context.measurement == measurement and context.sigma_v == 0.2
    assert context.system.h(np.array([0.3, 0.0])).tolist() == [0.5]
    training = context.training.simulate(_sinusoid(), 2, n_samples=9)
    assert np.isnan(training.y[:, 1:4]).all() and np.isfinite(training.y[:, [0, 4, 8]]).all()
    assert fit_context_for_row(spec, "ukf", "duffing", plain_tasks, 0).measurement == (
        PROTOCOL_CONDITIONS.measurement
    )


def _sinusoid():
    from kkl_bench.registry import regimes

    return regimes.get("sinusoid")()


def test_the_ekf_only_predicts_where_the_measurement_is_missing():
    measurement = MeasurementModel(observe_every=3, noise=NoiseLaw(sigma=0.01))
    context = conditioned_context(
        "duffing", 0, dataclasses.replace(PROTOCOL_CONDITIONS, measurement=measurement)
    )
    data = context.training.simulate(_sinusoid(), 2, n_samples=30)
    x_hat = variants.build("ekf").fit(context).estimate(data.t, data.y, data.u)
    for k in (1, 2, 4, 5):  # unobserved: the RK4 step of the previous estimate
        predicted = rk4_step(context.system, x_hat[:, k - 1], data.u[:, k - 1, 0], 0.05)
        assert np.allclose(x_hat[:, k], predicted, rtol=1e-12, atol=1e-12)
    for k in (3, 6):  # observed: updated
        predicted = rk4_step(context.system, x_hat[:, k - 1], data.u[:, k - 1, 0], 0.05)
        assert not np.allclose(x_hat[:, k], predicted, rtol=1e-6, atol=1e-6)
    for name in ("ukf", "enkf[inflation=1.0]", "particle_filter[n=200]"):
        estimate = variants.build(name).fit(context).estimate(data.t, data.y, data.u)
        assert np.isfinite(estimate).all(), name


class EverySampleOnly(Estimator):
    """A plugin that needs a measurement at every sample: the box centre, always."""

    supported_measurements = frozenset({"sensor", "noise"})

    def estimate(self, t, y, u):
        context = self.check_fitted()
        centre = (context.x0_low + context.x0_high) / 2
        return np.broadcast_to(centre, (len(y), len(t), len(centre))).copy()


def test_an_estimator_without_sparse_sampling_gets_unsupported_cells(
    sensing_track, register_estimator, tmp_path
):
    register_estimator("every_sample_only", EverySampleOnly)
    spec = RunSpec(
        ("every_sample_only",),
        ("duffing",),
        ("all-three",),
        get_profile("quick"),
        results_dir=tmp_path / "results",
        tracks=("sensing",),
    )
    summary = run(spec)
    assert summary.ok and [c.status for c in summary.unsupported] == ["unsupported"]
    cell = load_results(tmp_path / "results").iloc[0]
    assert cell["status"] == "unsupported"
    assert "another sampling than the protocol's (needs: sensor quantized" in cell["error"]


def test_held_keeps_the_last_measurement_over_the_missing_samples():
    nan = np.nan
    y = np.array([[[1.0, 10.0], [nan, nan], [nan, nan], [2.0, 20.0], [nan, nan]]])
    expected = [[[1.0, 10.0], [1.0, 10.0], [1.0, 10.0], [2.0, 20.0], [2.0, 20.0]]]
    assert held(y).tolist() == expected
    complete = np.ones((2, 3, 1))
    assert held(complete) is complete
    assert np.isnan(held(np.array([[[nan], [3.0], [nan]]]))[0, 0, 0])  # nothing to hold yet


def test_sequence_inputs_mark_the_measured_samples():
    y = np.array([[[1.0], [np.nan], [np.nan], [4.0]]])
    u = np.arange(4.0).reshape(1, 4, 1)
    yu = inputs(y, u, observed_channel=True).numpy()
    assert yu[0].tolist() == [[1, 0, 1], [1, 1, 0], [1, 2, 0], [4, 3, 1]]
    assert inputs(y, u, observed_channel=False).shape == (1, 4, 2)


def test_kalmannet_runs_the_open_loop_model_between_measurements():
    system = registry.systems.get("duffing")()
    network = KalmanNetFilter(system, 0.05, torch.zeros(2), 8, observed_channel=True)
    with torch.no_grad():  # a gain large enough that an update would show
        network.output[-1].bias.fill_(0.5)
    y = np.full((2, 7, 1), np.nan)
    y[:, ::3] = [[[0.3]], [[-0.2]]]
    u = np.full((2, 7, 1), 0.1)
    with torch.no_grad():
        x_hat = network(inputs(y, u, observed_channel=True))[0].double()
    for k in (1, 2, 4, 5):
        step = rk4_step(system, x_hat[:, k - 1], torch.full((2,), 0.1), 0.05)
        assert torch.allclose(x_hat[:, k], step, atol=1e-5)
    for k in (3, 6):
        step = rk4_step(system, x_hat[:, k - 1], torch.full((2,), 0.1), 0.05)
        assert not torch.allclose(x_hat[:, k], step, atol=1e-3)


def test_a_latent_observer_is_driven_by_the_held_measurement():
    observer = LatentObserver(*latent_matrices(np.array([1.0, 2.0, 3.0])), 0.05)
    y = np.sin(np.arange(40.0) / 5).reshape(1, 40, 1)
    sparse = np.where((np.arange(40) % 4 == 0)[None, :, None], y, np.nan)
    z = observer.run(sparse)
    assert np.isfinite(z).all()
    assert np.array_equal(z, observer.run(held(sparse)))
    assert not np.allclose(z, observer.run(y))


def test_headroom_measures_the_ukf_against_the_limit_on_validation_streams(capsys):
    from kkl_bench.cli import main

    assert (
        main(
            [
                "headroom",
                "--track",
                "hard",
                "--system",
                "duffing",
                "--regime",
                "quantized-square",
                "--trajectories",
                "1",
                "--limit",
                "particle_filter[n=100]",
            ]
        )
        == 0
    )
    line = capsys.readouterr().out.splitlines()[1].split()
    assert line[0] == "hard/duffing/quantized-square@v1"
    ukf, limit, ratio = map(float, line[1:])
    assert ratio == pytest.approx(ukf / limit, rel=1e-3)


def test_an_ensemble_that_blew_up_is_reported_as_diverged_not_raised():
    from kkl_bench.run.spec import conditioned_context as context_for

    enkf = variants.build("enkf[inflation=1.0]").fit(context_for("duffing", 0))
    ensemble = np.zeros((2, 24, 2))
    ensemble[0, 3, 1] = np.inf
    ensemble[1] = np.random.default_rng(0).normal(size=(24, 2))
    updated = enkf._analysis(enkf.context_.system, ensemble, np.array([[0.1], [0.2]]))
    assert np.isinf(updated[0]).any() and np.isfinite(updated[1]).all()
