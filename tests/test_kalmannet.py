"""KalmanNet against the Kalman filter on a linear system, where the exact gain is known."""

import numpy as np
import pytest
from kkl_bench.estimators.kalmannet import KalmanNet

from kkl_bench.registry import regimes
from tests.test_kkl import HarmonicOscillator, context_for
from tests.test_particle_filter import kalman_filter

BUDGET = dict(
    rnn_hidden=16,
    rnn_trajectories=32,
    rnn_validation=4,
    rnn_steps=60,
    rnn_batch=8,
    rnn_window=40,
    rnn_lr=3e-3,
)


@pytest.mark.slow
def test_kalmannet_approaches_the_kalman_filter_on_a_linear_system(tmp_path):
    context = context_for(HarmonicOscillator(), BUDGET, tmp_path)
    data = context.training.simulate(regimes.get("sinusoid")(), 8, stream="kn", n_samples=300)
    exact = kalman_filter(context, data)
    x_hat = KalmanNet().fit(context).estimate(data.t, data.y, data.u)

    def rms(estimate):
        return np.sqrt(np.mean((estimate[:, 50:] - data.x[:, 50:]) ** 2))

    optimal, learned = rms(exact), rms(x_hat)
    print(f"Kalman filter {optimal:.4f}, KalmanNet {learned:.4f}")
    assert learned < 1.3 * optimal


def test_the_warm_start_gain_is_the_steady_state_kalman_gain_on_a_linear_system(tmp_path):
    """On a linear system the EKF is the Kalman filter, whose gain converges to the one of
    the discrete algebraic Riccati equation: ``ekf_mean_gain`` averages it."""
    from kkl_bench.estimators.kalmannet import ekf_mean_gain
    from scipy.linalg import solve_discrete_are

    from kkl_bench.protocol.simulate import rk4_step_jacobian

    context = context_for(HarmonicOscillator(), BUDGET, tmp_path)
    system = context.system
    a = rk4_step_jacobian(system, np.zeros(2), np.asarray(0.0), context.dt)
    h = system.h_jacobian(np.zeros(2))
    q, r = context.sigma_w**2 * np.eye(2), context.sigma_v**2 * np.eye(1)
    prior = solve_discrete_are(a.T, h.T, q, r)
    expected = prior @ h.T @ np.linalg.inv(h @ prior @ h.T + r)
    np.testing.assert_allclose(ekf_mean_gain(context), expected, rtol=0.02)


def test_a_bad_gain_init_is_named():
    with pytest.raises(ValueError, match="gain_init='ones'; valid: zero, ekf"):
        KalmanNet(gain_init="ones")


@pytest.mark.parametrize(("gain_init", "scale"), [("zero", 1.0), ("ekf", 0.1)])
def test_the_warm_started_correction_trains_at_a_tenth_of_the_rate(
    tmp_path, monkeypatch, gain_init, scale
):
    """A correction to a filter that tracks takes smaller steps (protocol section 6.2)."""
    from kkl_bench.estimators import kalmannet

    seen = {}

    def capture(context, network, config, description):
        seen["lr"] = config.rnn_lr
        return {}

    monkeypatch.setattr(kalmannet, "fit_sequence_model", capture)
    context = context_for(HarmonicOscillator(), BUDGET, tmp_path)
    KalmanNet(gain_init=gain_init).fit(context)
    assert seen["lr"] == pytest.approx(scale * BUDGET["rnn_lr"])
