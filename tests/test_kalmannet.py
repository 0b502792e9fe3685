"""KalmanNet against the Kalman filter on a linear system, where the exact gain is known."""

import numpy as np
import pytest
from kkl_bench.estimators.learned.kalmannet import KalmanNet

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
    from kkl_bench.estimators.learned.kalmannet import ekf_mean_gain
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
    from kkl_bench.estimators.learned import kalmannet

    seen = {}

    def capture(context, network, config, description):
        seen["lr"] = config.rnn_lr
        return {}

    monkeypatch.setattr(kalmannet, "fit_sequence_model", capture)
    context = context_for(HarmonicOscillator(), BUDGET, tmp_path)
    KalmanNet(gain_init=gain_init).fit(context)
    assert seen["lr"] == pytest.approx(scale * BUDGET["rnn_lr"])


def test_the_compiled_step_computes_the_eager_steps_estimates_and_gradients():
    """``compile_step`` fuses the step's elementwise operations: over a window of 40
    samples of Duffing the estimates and every parameter's gradient agree with the eager
    step's to float32 rounding (protocol section 6.5)."""
    import torch
    from kkl_bench.estimators.learned.kalmannet import KalmanNetFilter

    from kkl_bench.registry import systems
    from kkl_bench.support.devices import compile_failure

    if compile_failure() is not None:
        pytest.skip(f"torch.compile fails here: {compile_failure()}")
    system = systems.get("duffing")()
    yu = torch.randn(8, 40, 2, generator=torch.Generator().manual_seed(0))
    runs = []
    for compiled in (False, True):
        torch.manual_seed(0)
        network = KalmanNetFilter(system, 0.05, torch.zeros(2), 16, observed_channel=False)
        if compiled:
            network.compile_step()
        x_hat, _ = network(yu)
        x_hat.pow(2).mean().backward()
        runs.append([x_hat.detach(), *(p.grad for p in network.parameters())])
    for eager, compiled in zip(*runs, strict=True):
        torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("asked", "failure", "compiled"),
    [(False, None, False), (True, None, True), (True, "NoCompiler: no g++", False)],
)
def test_a_fit_compiles_its_step_when_its_budget_asks_and_torch_can(
    tmp_path, monkeypatch, asked, failure, compiled
):
    """The model is cached under whether its step was compiled; where torch cannot
    compile, a warning names why and training runs eagerly."""
    from kkl_bench.estimators.learned import kalmannet

    seen = {}

    def capture(context, network, config, description):
        seen["description"], seen["network"] = description, network
        return {}

    monkeypatch.setattr(kalmannet, "fit_sequence_model", capture)
    monkeypatch.setattr(kalmannet, "compile_failure", lambda: failure)
    context = context_for(HarmonicOscillator(), {**BUDGET, "compile_step": asked}, tmp_path)
    if failure:
        with pytest.warns(UserWarning, match="torch.compile fails on this machine .NoCompiler"):
            KalmanNet().fit(context)
    else:
        KalmanNet().fit(context)
    assert ("compiled_step" in seen["description"]) == compiled
    assert (seen["network"].compiled_step is not None) == compiled
