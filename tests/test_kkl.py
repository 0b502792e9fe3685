"""The KKL toolkit and plugins against known answers."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from kkl_bench.estimators.injection_kkl import exact_injection
from scipy.integrate import solve_ivp
from scipy.linalg import solve_sylvester

from kkl_bench.estimator import FitContext
from kkl_bench.kkl import autonomous, optimize
from kkl_bench.kkl.autonomous import Phase1Config, fit_autonomous
from kkl_bench.kkl.hyper import ChunkedHead, LowRankHead, make_head
from kkl_bench.kkl.latent import LatentObserver, latent_matrices, spread_eigenvalues
from kkl_bench.kkl.networks import NormalizedMLP
from kkl_bench.kkl.pde import pde_residual
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import estimators, regimes, systems
from kkl_bench.training import TrainingData

TINY = dict(
    hidden=32,
    train_trajectories=8,
    encoder_steps=150,
    decoder_steps=150,
    selection_steps=30,
    rate_candidates=[[1.0, 5.0], [2.0, 10.0]],
    phase2_trajectories=8,
    phase2_steps=40,
    window=20,
    lstm_hidden=8,
    curriculum_epoch_steps=5,
    max_epochs=6,
)


def context_for(system, budget, cache_dir, seed=0):
    return FitContext(
        system=system,
        dt=DT,
        n_samples=N_SAMPLES,
        sigma_w=SIGMA_W,
        sigma_v=SIGMA_V,
        training=TrainingData(system, DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed),
        seed=seed,
        profile="test",
        budget=budget,
        cache_dir=cache_dir,
    )


class HarmonicOscillator(MeasureOneState):
    """``dx1 = x2``, ``dx2 = -x1 + u``, ``y = x1``: its KKL map is linear, ``T(x) = M x``."""

    name = "harmonic"
    state_names = ("x1", "x2")
    g = np.array([0.0, 1.0])
    x0_low = np.array([-1.0, -1.0])
    x0_high = np.array([1.0, 1.0])
    measured = 0
    F = np.array([[0.0, 1.0], [-1.0, 0.0]])

    def f(self, x):
        return stack([x[..., 1], -x[..., 0]])

    def f_jacobian(self, x):
        return np.broadcast_to(self.F, (*x.shape[:-1], 2, 2)).copy()


def test_latent_observer_is_exact_for_piecewise_linear_output():
    a, b = latent_matrices(spread_eigenvalues(5, 1.0, 20.0))
    observer = LatentObserver(a, b, 0.05)
    y = np.random.default_rng(0).normal(size=(1, 6, 1))

    def y_of(t):  # first-order hold between samples
        k = min(int(t / 0.05), 4)
        return y[0, k, 0] + (y[0, k + 1, 0] - y[0, k, 0]) * (t - 0.05 * k) / 0.05

    z0 = observer.initial_state(y[:, 0])
    reference = solve_ivp(
        lambda t, z: a @ z + b[:, 0] * y_of(t),
        (0, 0.25),
        z0[0],
        rtol=1e-12,
        atol=1e-12,
        t_eval=0.05 * np.arange(6),
    )
    np.testing.assert_allclose(observer.run(y)[0], reference.y.T, atol=1e-9)


def test_held_injection_gain_is_exact():
    a, b = latent_matrices(spread_eigenvalues(5, 1.0, 5.0))
    observer = LatentObserver(a, b, 0.05)
    injection = np.arange(1.0, 6.0)
    reference = solve_ivp(
        lambda t, z: a @ z + injection, (0, 0.05), np.zeros(5), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(observer.injection_gain @ injection, reference.y[:, -1], atol=1e-10)


def test_uncontrollable_or_unstable_latent_pairs_are_refused():
    with pytest.raises(ValueError, match="distinct and positive"):
        latent_matrices(np.array([1.0, 1.0, 2.0]))


def test_pde_residual_by_jvp_equals_residual_by_explicit_jacobian():
    torch.manual_seed(0)
    encoder = NormalizedMLP(3, 7, 16, 2)
    system = systems.get("lorenz")()
    a, b = (
        torch.as_tensor(m, dtype=torch.float32)
        for m in latent_matrices(spread_eigenvalues(7, 1.0, 10.0))
    )
    x = 5 * torch.randn(32, 3)
    by_jvp = pde_residual(encoder, x, system.f(x), system.h(x), a, b)
    jacobians = torch.stack([torch.autograd.functional.jacobian(encoder, point) for point in x])
    explicit = (
        torch.einsum("bzx,bx->bz", jacobians, system.f(x)) - encoder(x) @ a.T - system.h(x) @ b.T
    )
    torch.testing.assert_close(by_jvp, explicit, rtol=1e-4, atol=1e-4)


def test_perturbed_forward_with_zero_deltas_matches_the_base_network():
    torch.manual_seed(0)
    network = NormalizedMLP(2, 5, 16, 3)
    x = torch.randn(4, 3, 2)
    zero = [(torch.zeros(4, *w), torch.zeros(4, *bias)) for w, bias in network.parameter_shapes()]
    torch.testing.assert_close(network(x, zero), network(x))


@pytest.mark.parametrize("head", ["chunked", "lowrank"])
def test_heads_give_zero_perturbation_for_the_zero_context(head):
    torch.manual_seed(0)
    shapes = NormalizedMLP(5, 2, 16, 2).parameter_shapes()
    module = make_head(head, shapes, context=8, chunk=100, rank=2)
    for parameter in module.parameters():  # move away from the zero initialization
        torch.nn.init.normal_(parameter)
    c0 = torch.randn(1, 8).expand(3, -1)
    for (d_weight, d_bias), (weight_shape, bias_shape) in zip(module(c0, c0), shapes, strict=True):
        assert d_weight.shape == (3, *weight_shape) and d_bias.shape == (3, *bias_shape)
        assert torch.count_nonzero(d_weight) == 0 and torch.count_nonzero(d_bias) == 0
    assert any(torch.count_nonzero(w) for w, _ in module(torch.randn(3, 8), c0))
    assert isinstance(module, ChunkedHead if head == "chunked" else LowRankHead)


def test_unknown_head_lists_the_valid_ones():
    with pytest.raises(
        ValueError, match="unknown hypernetwork head 'dense'; valid heads: chunked, lowrank"
    ):
        make_head("dense", [], 4, 8, 2)


@pytest.fixture(scope="module")
def harmonic(tmp_path_factory):
    """autonomous_kkl and injection_kkl fitted on the harmonic oscillator (one shared Phase 1)."""
    context = context_for(
        HarmonicOscillator(),
        {**TINY, "encoder_steps": 1500, "decoder_steps": 800, "rate_candidates": [[1.0, 5.0]]},
        tmp_path_factory.mktemp("harmonic-cache"),
    )
    return {
        name: estimators.get(name)().fit(context) for name in ("autonomous_kkl", "injection_kkl")
    }


def harmonic_data(regime, seed=7):
    system = HarmonicOscillator()
    return TrainingData(system, DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed).simulate(
        regimes.get(regime)(), 4, stream="check"
    )


def test_autonomous_kkl_learns_the_sylvester_map_of_a_linear_system(harmonic):
    model = harmonic["autonomous_kkl"].model_
    exact = solve_sylvester(
        model.observer.a, -HarmonicOscillator.F, -model.observer.b @ np.array([[1.0, 0.0]])
    )  # A M - M F = -B H
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (256, 2))
    x = x / np.linalg.norm(x, axis=1, keepdims=True) * np.sqrt(rng.uniform(0.3, 1.0, (256, 1)))
    with torch.no_grad():
        learned = model.encoder(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
    assert np.linalg.norm(learned - x @ exact.T) / np.linalg.norm(x @ exact.T) < 0.05
    data = harmonic_data("zero")
    error = np.abs(harmonic["autonomous_kkl"].estimate(data.t, data.y, data.u) - data.x)
    assert error[:, :100].mean() > 2 * error[:, 500:].mean()  # the estimate converges
    assert error[:, 500:].mean() < 0.05


def test_injection_of_an_exact_linear_map_is_exactly_m_g():
    """With ``T(x) = M x``, the injection ``dT/dx(T*(z)) g u`` is ``M g u`` whatever ``z``."""
    rates = spread_eigenvalues(5, 1.0, 5.0)
    a, b = latent_matrices(rates)
    exact = solve_sylvester(a, -HarmonicOscillator.F, -b @ np.array([[1.0, 0.0]]))
    encoder = torch.nn.Linear(2, 5, bias=False)
    decoder = torch.nn.Linear(5, 2, bias=False)
    with torch.no_grad():
        encoder.weight.copy_(torch.as_tensor(exact))
        decoder.weight.copy_(torch.as_tensor(np.linalg.pinv(exact)))
    model = SimpleNamespace(encoder=encoder, decoder=decoder)
    u = np.array([[[0.5]], [[-2.0]]])
    phi = exact_injection(model, HarmonicOscillator.g, u)(
        0, np.random.default_rng(0).normal(size=(2, 5))
    )
    np.testing.assert_allclose(
        phi, u[:, 0] * (exact @ HarmonicOscillator.g).astype(np.float32), rtol=1e-6
    )


def test_injection_kkl_converges_under_input_where_the_autonomous_observer_cannot(harmonic):
    data = harmonic_data("square")
    late = slice(500, None)
    injected = np.abs(harmonic["injection_kkl"].estimate(data.t, data.y, data.u) - data.x)[
        :, late
    ].mean()
    ignoring = np.abs(harmonic["autonomous_kkl"].estimate(data.t, data.y, data.u) - data.x)[
        :, late
    ].mean()
    assert injected < 0.1 and injected < ignoring / 2


@pytest.fixture(scope="module")
def fitted_family(tmp_path_factory):
    """The four KKL plugins fitted with a tiny budget on duffing, sharing one cache."""
    cache = tmp_path_factory.mktemp("kkl-cache")
    context = context_for(systems.get("duffing")(), TINY, cache)
    names = (
        "autonomous_kkl",
        "static_hyperkkl",
        "dynamic_hyperkkl",
        "curriculum_kkl",
        "injection_kkl",
    )
    return {name: estimators.get(name)().fit(context) for name in names}


@pytest.mark.parametrize("name", ["static_hyperkkl", "dynamic_hyperkkl", "injection_kkl"])
def test_zero_input_reproduces_the_autonomous_observer_exactly(fitted_family, name):
    data = TrainingData(systems.get("duffing")(), DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed=3).simulate(
        regimes.get("zero")(), 3, stream="check", n_samples=300
    )
    reference = fitted_family["autonomous_kkl"].estimate(data.t, data.y, data.u)
    np.testing.assert_array_equal(fitted_family[name].estimate(data.t, data.y, data.u), reference)
    forced = TrainingData(
        systems.get("duffing")(), DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed=3
    ).simulate(regimes.get("square")(), 3, stream="check", n_samples=300)
    assert not np.array_equal(
        fitted_family[name].estimate(forced.t, forced.y, forced.u),
        fitted_family["autonomous_kkl"].estimate(forced.t, forced.y, forced.u),
    )


def test_low_rank_heads_also_reproduce_the_autonomous_observer_at_zero_input(
    fitted_family, tmp_path
):
    context = context_for(systems.get("duffing")(), TINY, tmp_path)
    low_rank = estimators.get("dynamic_hyperkkl")(head="lowrank", rank=4).fit(context)
    data = TrainingData(systems.get("duffing")(), DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed=3).simulate(
        regimes.get("zero")(), 2, stream="check", n_samples=200
    )
    np.testing.assert_array_equal(
        low_rank.estimate(data.t, data.y, data.u),
        fitted_family["autonomous_kkl"].estimate(data.t, data.y, data.u),
    )
    assert low_rank.get_params()["head"] == "lowrank"


def test_fit_report_records_rates_selection_quality_and_log(fitted_family):
    report = fitted_family["dynamic_hyperkkl"].fit_report()
    assert len(report["latent_rates"]) == 5 and set(report["rate_selection"]) == {"1-5", "2-10"}
    assert set(report["map_quality"]) == {
        "reconstruction_rmse_unforced",
        "reconstruction_rmse_forced",
        "pde_residual_unforced",
        "pde_residual_forced",
    }
    assert all(np.isfinite(value) and value >= 0 for value in report["map_quality"].values())
    assert "final_loss" in report["training_log"]
    assert "training_log" not in fitted_family["autonomous_kkl"].fit_report()


def test_curriculum_walks_every_level_and_records_it(fitted_family):
    log = fitted_family["curriculum_kkl"].log_
    assert list(log) == [
        "constant",
        "sine 0.2-0.8 rad/s",
        "sine 0.8-2.5 rad/s",
        "square 2-10 s",
        "multi-sine",
    ]
    assert all(5 <= level["epochs"] <= 6 for level in log.values())


def test_checkpoints_are_reused_and_invalidated(tmp_path, monkeypatch):
    calls = []
    original = optimize.minimize

    def counting(*args, **kwargs):
        calls.append(kwargs.get("description"))
        return original(*args, **kwargs)

    monkeypatch.setattr(autonomous, "minimize", counting)
    system = systems.get("vdp")()
    config = Phase1Config(
        hidden=16,
        encoder_steps=20,
        decoder_steps=20,
        selection_steps=5,
        train_trajectories=4,
        rate_candidates=((1.0, 5.0),),
    )
    first = fit_autonomous(context_for(system, TINY, tmp_path), config)
    assert len(calls) == 3  # rate selection, encoder, decoder
    again = fit_autonomous(context_for(system, TINY, tmp_path), config)
    assert len(calls) == 3  # loaded, not retrained
    for parameter, reloaded in zip(
        first.decoder.parameters(), again.decoder.parameters(), strict=True
    ):
        torch.testing.assert_close(parameter, reloaded)
    fit_autonomous(
        context_for(system, TINY, tmp_path), dataclasses.replace(config, encoder_steps=21)
    )
    assert len(calls) == 6  # a changed budget retrains
    fit_autonomous(context_for(system, TINY, tmp_path, seed=1), config)
    assert len(calls) == 9  # so does another seed
