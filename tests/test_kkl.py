"""The KKL toolkit and plugins against known answers."""

import dataclasses
import shutil

import numpy as np
import pytest
import torch
from kkl_bench.estimators.learned.dynamic_hyperkkl import SHARED_WINDOW
from kkl_bench.estimators.learned.injection_kkl import ExactInjection
from scipy.integrate import solve_ivp
from scipy.linalg import solve_sylvester

from kkl_bench.estimator import FitContext
from kkl_bench.kkl import autonomous, optimize
from kkl_bench.kkl import decoder as decoder_module
from kkl_bench.kkl.autonomous import AutonomousModel, Phase1Config, fit_autonomous, phase1_rule
from kkl_bench.kkl.boxes import training_boxes
from kkl_bench.kkl.frozen import FrozenMLP
from kkl_bench.kkl.gain import select_gain
from kkl_bench.kkl.hyper import ChunkedHead, LowRankHead, make_head
from kkl_bench.kkl.latent import (
    LatentObserver,
    latent_drift,
    latent_matrices,
    spread_eigenvalues,
)
from kkl_bench.kkl.networks import NormalizedMLP, affine_normalization
from kkl_bench.kkl.pde import directional_derivative, pde_residual
from kkl_bench.kkl.plateau import PlateauRule
from kkl_bench.kkl.windows import WindowEncoder, distinct, embed, is_active, sliding_windows
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
    curriculum_steps=30,
    validate_every=10,
    plateau_patience=2,
    plateau_reductions=1,
    adaptation_steps=40,
    adaptation_trajectories=8,
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


def test_pde_residual_by_forward_tangent_equals_residual_by_explicit_jacobian():
    torch.manual_seed(0)
    encoder = NormalizedMLP(3, 7, 16, 2)
    system = systems.get("lorenz")()
    a, b = (
        torch.as_tensor(m, dtype=torch.float32)
        for m in latent_matrices(spread_eigenvalues(7, 1.0, 10.0))
    )
    x = 5 * torch.randn(32, 3)
    by_tangent = pde_residual(encoder, x, system.f(x), system.h(x), a, b)
    jacobians = torch.stack([torch.autograd.functional.jacobian(encoder, point) for point in x])
    explicit = (
        torch.einsum("bzx,bx->bz", jacobians, system.f(x)) - encoder(x) @ a.T - system.h(x) @ b.T
    )
    torch.testing.assert_close(by_tangent, explicit, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("perturbed", [False, True])
def test_forward_tangent_equals_torch_func_jvp_values_and_parameter_gradients(perturbed):
    torch.manual_seed(0)
    network = NormalizedMLP(3, 5, 16, 3)
    network.set_normalization(2 * torch.randn(200, 3) + 1, torch.randn(200, 5) @ torch.randn(5, 5))
    x, v = torch.randn(4, 6, 3), torch.randn(4, 6, 3)
    deltas = None
    if perturbed:  # a hypernetwork's per-window weight perturbations
        deltas = [
            (0.1 * torch.randn(4, *w), 0.1 * torch.randn(4, *b))
            for w, b in network.parameter_shapes()
        ]
    value, tangent = network.forward_with_tangent(x, v, deltas)
    (tangent.square().sum() + value.sum()).backward()
    ours = [p.grad.clone() for p in network.parameters()]
    network.zero_grad()
    value_ref, tangent_ref = torch.func.jvp(lambda s: network(s, deltas), (x,), (v,))
    (tangent_ref.square().sum() + value_ref.sum()).backward()
    torch.testing.assert_close(value, value_ref)
    torch.testing.assert_close(tangent, tangent_ref, rtol=1e-5, atol=1e-5)
    for mine, reference in zip(ours, (p.grad for p in network.parameters()), strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-5)


def test_whitening_gives_unit_covariance_and_colouring_inverts_it():
    rng = np.random.default_rng(0)
    mixing = np.array([[1.0, 0.999, 0.998], [0.0, 1e-1, 2e-1], [0.0, 0.0, 1e-2]])
    samples = torch.as_tensor(rng.normal(size=(20000, 3)) @ mixing + 5.0)
    mean, whitening, coloring = affine_normalization(samples, whiten=True)
    whitened = (samples - mean.double()) @ whitening.double()
    np.testing.assert_allclose(torch.cov(whitened.T).numpy(), np.eye(3), atol=2e-3)
    np.testing.assert_allclose(
        (whitening.double() @ coloring.double()).numpy(), np.eye(3), atol=1e-4
    )
    _, scaling, unscaling = affine_normalization(samples, whiten=False)
    np.testing.assert_allclose(torch.diag(unscaling).numpy(), samples.std(0).numpy(), rtol=1e-6)
    assert torch.count_nonzero(scaling - torch.diag(torch.diag(scaling))) == 0


def test_whitening_floors_directions_without_variance():
    rng = np.random.default_rng(0)
    plane = rng.normal(size=(5000, 2)) @ rng.normal(size=(2, 4))  # rank 2 in 4 dimensions
    _, whitening, _ = affine_normalization(torch.as_tensor(plane), whiten=True, floor=1e-6)
    assert torch.linalg.matrix_norm(whitening, ord=2) < 1e4  # finite, not 1/0


def test_normalized_mlp_maps_physical_units_through_whitened_coordinates():
    torch.manual_seed(0)
    network = NormalizedMLP(3, 2, 8, 2)
    inputs = torch.randn(500, 3) @ torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.1, 0.0], [0, 0, 0.01]])
    outputs = torch.randn(500, 2) * torch.tensor([3.0, 0.5]) + 7.0
    network.set_normalization(inputs, outputs)
    x = inputs[:4]
    expected = network.out_mean + network.normalized(
        (x - network.in_mean) @ network.in_whitening
    ) @ torch.diag(outputs.std(0))
    torch.testing.assert_close(network(x), expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(
        network.output_difference(torch.tensor([3.0, 0.5])),
        torch.tensor([1.0, 1.0]) * torch.tensor([3.0, 0.5]) / outputs.std(0),
    )


def test_frozen_mlp_equals_the_torch_network_and_its_tangent():
    torch.manual_seed(0)
    network = NormalizedMLP(3, 5, 32, 3)
    network.set_normalization(
        torch.randn(400, 3) * torch.tensor([1.0, 10.0, 0.1]) + 2.0,
        torch.randn(400, 5) @ torch.randn(5, 5),
        whiten_outputs=True,
    )
    x, v = torch.randn(20, 3), torch.tensor([0.0, 1.0, 0.5])
    directions = torch.randn(20, 3)
    with torch.no_grad():
        value, tangent = network.forward_with_tangent(x, v.expand_as(x))
        _, tangents = network.forward_with_tangent(x, directions)
    frozen = FrozenMLP.of(network)
    frozen_value, frozen_tangent = frozen.with_tangent(x.numpy(), v.numpy())
    _, frozen_tangents = frozen.with_tangent(x.numpy(), directions.numpy())
    for got, expected in (
        (frozen(x.numpy()), value),
        (frozen_value, value),
        (frozen_tangent, tangent),
        (frozen_tangents, tangents),
    ):
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, expected.numpy(), rtol=0, atol=1e-5 * expected.abs().max())


def test_frozen_mlp_splits_a_known_part_of_its_input_off():
    torch.manual_seed(1)
    layers = [torch.nn.Linear(5, 8), torch.nn.Linear(8, 2)]
    frozen = FrozenMLP.from_layers(layers)
    rng = np.random.default_rng(0)
    a, c = rng.normal(size=(4, 3)).astype(np.float32), rng.normal(size=(4, 2)).astype(np.float32)
    first, weight = frozen.split_input(3)
    np.testing.assert_allclose(first(a, offset=c @ weight), frozen(np.hstack([a, c])), atol=1e-6)
    with pytest.raises(
        TypeError, match="cannot freeze a Sequential; expected NormalizedMLP or Linear"
    ):
        FrozenMLP.of(torch.nn.Sequential(*layers))


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
    """autonomous_kkl and the pure injection_kkl on the harmonic oscillator (one Phase 1)."""
    context = context_for(
        HarmonicOscillator(),
        {
            **TINY,
            "encoder_steps": 1500,
            "decoder_steps": 800,
            "rate_candidates": [[1.0, 5.0]],
            **{"validate_every": 50, "plateau_patience": 4, "plateau_reductions": 3},
        },
        tmp_path_factory.mktemp("harmonic-cache"),
    )
    return {
        "autonomous_kkl": estimators.get("autonomous_kkl")().fit(context),
        "injection_kkl": estimators.get("injection_kkl")(adapt=False).fit(context),
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


def exact_linear_model() -> AutonomousModel:
    """The harmonic oscillator's exact KKL maps: ``T(x) = M x`` (Sylvester), ``T*(z) = M^+ z``."""
    rates = spread_eigenvalues(5, 1.0, 5.0)
    a, b = latent_matrices(rates)
    exact = solve_sylvester(a, -HarmonicOscillator.F, -b @ np.array([[1.0, 0.0]]))
    encoder = torch.nn.Linear(2, 5, bias=False)
    decoder = torch.nn.Linear(5, 2, bias=False)
    with torch.no_grad():
        encoder.weight.copy_(torch.as_tensor(exact))
        decoder.weight.copy_(torch.as_tensor(np.linalg.pinv(exact)))
    return AutonomousModel(rates, LatentObserver(a, b, DT), encoder, decoder)


def test_injection_of_an_exact_linear_map_is_exactly_m_g():
    """With ``T(x) = M x``, the injection ``dT/dx(T*(z)) g u`` is ``M g u`` whatever ``z``."""
    model = exact_linear_model()
    exact = model.encoder.weight.detach().double().numpy()
    u = np.array([[[0.5]], [[-2.0]]])
    phi = ExactInjection(model, HarmonicOscillator.g, u)(
        0, np.random.default_rng(0).normal(size=(2, 5))
    )
    np.testing.assert_allclose(
        phi, u[:, 0] * (exact @ HarmonicOscillator.g).astype(np.float32), rtol=1e-6
    )


def test_gain_selection_keeps_the_full_injection_of_exact_maps(tmp_path):
    context = context_for(HarmonicOscillator(), TINY, tmp_path)
    model = exact_linear_model()
    gain, scores = select_gain(
        context,
        model,
        lambda u, gain: ExactInjection(model, HarmonicOscillator.g, u, gain),
        4,
        "check",
    )
    assert gain == 1.0 and scores["1"] < scores["0"] / 10


def test_gain_selection_ranks_a_diverging_gain_last(tmp_path):
    context = context_for(HarmonicOscillator(), TINY, tmp_path)
    model = exact_linear_model()

    def injection_for(u, gain):
        exact = ExactInjection(model, HarmonicOscillator.g, u, 1.0)
        if gain == 1.0:
            return lambda k, z: exact(k, z) + (np.nan if k == 500 else 0.0)
        return lambda k, z: gain * exact(k, z)

    gain, scores = select_gain(context, model, injection_for, 4, "check", gains=(0.0, 0.5, 1.0))
    assert scores["1"] == float("inf") and gain == 0.5


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
    """The KKL plugins fitted with a tiny budget on duffing, sharing one cache
    (``pure_injection_kkl``: injection_kkl without adaptation; ``guarded_static_hyperkkl``:
    static_hyperkkl with a validated gain; the default is the paper's gain 1)."""
    cache = tmp_path_factory.mktemp("kkl-cache")
    context = context_for(systems.get("duffing")(), TINY, cache)
    names = (
        "autonomous_kkl",
        "static_hyperkkl",
        "dynamic_hyperkkl",
        "curriculum_kkl",
        "injection_kkl",
    )
    family = {name: estimators.get(name)().fit(context) for name in names}
    family["pure_injection_kkl"] = estimators.get("injection_kkl")(adapt=False).fit(context)
    family["guarded_static_hyperkkl"] = estimators.get("static_hyperkkl")(guard=True).fit(context)
    return family


class Interrupted(Exception):
    """Stands for a kill in the middle of a training."""


@pytest.fixture(scope="module")
def duffing_phase1(tmp_path_factory):
    """A cache holding the TINY Phase-1 model of duffing."""
    cache = tmp_path_factory.mktemp("phase1")
    autonomous.fit_phase1(context_for(systems.get("duffing")(), TINY, cache), pde_weight=1.0)
    return cache


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, interrupt_after",
    # dynamic_hyperkkl trains through fit_phase2 exactly as static_hyperkkl does
    [("static_hyperkkl", 25), ("curriculum_kkl", 12), ("injection_kkl", 25)],
)
def test_an_interrupted_phase2_training_resumes_from_its_checkpoint_with_the_same_result(
    tmp_path, monkeypatch, duffing_phase1, name, interrupt_after
):
    monkeypatch.setattr(optimize, "CHECKPOINT_EVERY", 10)
    adam_step = torch.optim.Adam.step
    steps = {"taken": 0, "limit": None}

    def counted_step(self, *args, **kwargs):
        if steps["taken"] == steps["limit"]:
            raise Interrupted
        steps["taken"] += 1
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", counted_step)
    system = systems.get("duffing")()
    data = duffing_data("square")
    reference_cache, cache = tmp_path / "reference", tmp_path / "interrupted"
    for target in (reference_cache, cache):  # the same Phase 1 for both
        shutil.copytree(duffing_phase1, target)
    steps["taken"] = 0
    reference = estimators.get(name)().fit(context_for(system, TINY, reference_cache))
    total = steps["taken"]
    assert total > interrupt_after

    steps.update(taken=0, limit=interrupt_after)
    with pytest.raises(Interrupted):
        estimators.get(name)().fit(context_for(system, TINY, cache))
    assert list((cache / optimize.RESUME_KIND).glob("*.pt"))  # its checkpoints survived
    steps.update(taken=0, limit=None)
    resumed = estimators.get(name)().fit(context_for(system, TINY, cache))
    assert steps["taken"] < total  # it did not start again from nothing
    np.testing.assert_array_equal(
        resumed.estimate(data.t, data.y, data.u), reference.estimate(data.t, data.y, data.u)
    )
    assert effort(resumed.fit_report()["spent"]) == effort(reference.fit_report()["spent"])
    assert not list((cache / optimize.RESUME_KIND).glob("*.pt"))  # removed once saved


def duffing_data(regime, n_samples=300):
    return TrainingData(systems.get("duffing")(), DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed=3).simulate(
        regimes.get(regime)(), 3, stream="check", n_samples=n_samples
    )


@pytest.mark.parametrize("name", ["static_hyperkkl", "dynamic_hyperkkl", "pure_injection_kkl"])
def test_zero_input_reproduces_the_autonomous_observer_exactly(fitted_family, name):
    data = duffing_data("zero")
    reference = fitted_family["autonomous_kkl"].estimate(data.t, data.y, data.u)
    np.testing.assert_array_equal(fitted_family[name].estimate(data.t, data.y, data.u), reference)
    forced = duffing_data("square")
    assert not np.array_equal(
        fitted_family[name].estimate(forced.t, forced.y, forced.u),
        fitted_family["autonomous_kkl"].estimate(forced.t, forced.y, forced.u),
    )


def torch_injection(estimator, u):
    """The injection of ``injection_kkl`` or ``static_hyperkkl`` evaluated by the torch
    networks themselves, sample by sample (the path the frozen copies replaced)."""
    model, gain = estimator.model_, estimator.gain_
    encoder = model.encoder
    if estimator.name == "injection_kkl":
        g = torch.as_tensor(estimator.check_fitted().system.g, dtype=torch.float32)

        def injection(k, z):
            x_hat = model.decoder(torch.as_tensor(z, dtype=torch.float32))
            _, along_g = directional_derivative(encoder, x_hat, g.expand_as(x_hat))
            return gain * u[:, k] * along_g.double().numpy()

        return injection
    windows = sliding_windows(u, estimator.config_.window)
    contexts = estimator.injection_.window_encoder(windows.flatten(0, 1)).unflatten(0, u.shape[:2])

    def injection(k, z):
        z_tilde = encoder.normalized_output(torch.as_tensor(z, dtype=torch.float32))
        psi = estimator.injection_(z_tilde, contexts[:, k]) @ encoder.out_coloring
        return gain * u[:, k] * psi.double().numpy()

    return injection


@pytest.mark.parametrize("regime", ["sinusoid", "square"])  # square repeats its windows
@pytest.mark.parametrize("name", ["static_hyperkkl", "pure_injection_kkl"])
def test_frozen_networks_give_the_torch_networks_estimates(fitted_family, name, regime):
    estimator = fitted_family[name]
    data = duffing_data(regime)
    with torch.no_grad():
        z = estimator.model_.observer.run(data.y, torch_injection(estimator, data.u))
    reference = estimator.model_.decode(z)
    estimate = estimator.estimate(data.t, data.y, data.u)
    assert not np.array_equal(
        reference, fitted_family["autonomous_kkl"].estimate(data.t, data.y, data.u)
    )
    np.testing.assert_allclose(estimate, reference, rtol=0, atol=1e-4 * np.abs(reference).max())


@pytest.mark.parametrize("regime", ["sinusoid", "square", "constant"])
def test_dynamic_hyperkkl_estimates_equal_per_sample_weight_generation(fitted_family, regime):
    """The estimate generates weights once per distinct window and applies a window shared
    by many samples to all of them at once; generating them for every sample from its own
    window, as the training does, gives the same estimates."""
    estimator = fitted_family["dynamic_hyperkkl"]
    data = duffing_data(regime)
    z = estimator.model_.observer.run(data.y)
    windows = sliding_windows(data.u, estimator.config_.window).flatten(0, 1)
    with torch.no_grad():
        contexts, zero = estimator.hyper_.contexts(windows)
        deltas = estimator.hyper_.decoder_head(contexts, zero)
        z_flat = torch.as_tensor(z.reshape(-1, 1, z.shape[-1]), dtype=torch.float32)
        reference = estimator.model_.decoder(z_flat, deltas)[:, 0].double().numpy()
    estimate = estimator.estimate(data.t, data.y, data.u).reshape(reference.shape)
    active = is_active(windows).numpy()
    counts = torch.bincount(distinct(windows[active])[1])
    assert active.any() and (regime == "sinusoid" or len(counts) < len(windows) / 2)
    assert (regime == "sinusoid") != bool((counts >= SHARED_WINDOW).any())
    np.testing.assert_allclose(
        estimate[active], reference[active], rtol=0, atol=1e-5 * np.abs(reference).max()
    )


def test_window_embeddings_are_computed_once_per_distinct_window():
    torch.manual_seed(0)
    encoder = WindowEncoder(8)
    windows = torch.randn(5, 11)[torch.tensor([0, 1, 0, 2, 3, 4, 1, 1])]
    calls = []
    encoder.register_forward_hook(lambda module, args, out: calls.append(len(args[0])))
    embedded = embed(encoder, windows)
    assert calls == [5]
    with torch.no_grad():
        np.testing.assert_allclose(embedded, encoder(windows), rtol=0, atol=1e-6)
    assert embed(encoder, windows[:0]).shape == (0, 8)


def test_guarded_static_hyperkkl_uses_the_gain_with_the_best_validation_score(fitted_family):
    guarded, unguarded = (
        fitted_family["guarded_static_hyperkkl"],
        fitted_family["static_hyperkkl"],
    )
    scores = guarded.log_["gain_selection"]
    assert set(scores) == {"0", "0.25", "0.5", "0.75", "1"} and unguarded.gain_ == 1.0
    assert scores[f"{guarded.gain_:g}"] == min(scores.values())
    data = duffing_data("zero")  # any gain keeps the zero-input observer
    np.testing.assert_array_equal(
        guarded.estimate(data.t, data.y, data.u),
        fitted_family["autonomous_kkl"].estimate(data.t, data.y, data.u),
    )


def test_adapted_injection_kkl_trains_a_copy_of_the_decoder_and_logs_its_rounds(fitted_family):
    adapted, pure = fitted_family["injection_kkl"], fitted_family["pure_injection_kkl"]
    log = adapted.fit_report()["training_log"]
    rounds = [f"round {i}" for i in range(1, 5)]
    kept = ["rounds_curve", "best_round", "spent"]
    assert list(log) == ["injection_gain", "gain_selection", *rounds, *kept]
    # the injected observer's validation RMSE before adapting and after each round, which
    # ends by the plateau rule within its share of the cap (40 steps over 4 rounds)
    steps = [log[round_]["steps"] for round_ in rounds]
    assert all(1 <= taken <= 10 for taken in steps)
    assert [step for step, _ in log["rounds_curve"]] == [0, *np.cumsum(steps).tolist()]
    errors = [error for _, error in log["rounds_curve"]]
    assert errors[log["best_round"]] == min(errors)
    assert set(log["gain_selection"]) == {"0", "0.25", "0.5", "0.75", "1"}
    assert log["injection_gain"] == adapted.gain_ and pure.gain_ == 1.0
    assert "training_log" not in pure.fit_report()
    assert any(
        not torch.equal(a, b)
        for a, b in zip(
            adapted.model_.decoder.parameters(), pure.model_.decoder.parameters(), strict=True
        )
    )
    torch.testing.assert_close(  # the shared Phase-1 encoder is untouched
        dict(adapted.model_.encoder.state_dict()), dict(pure.model_.encoder.state_dict())
    )
    data = duffing_data("square")
    assert np.isfinite(adapted.estimate(data.t, data.y, data.u)).all()


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
    log = {
        key: value for key, value in fitted_family["curriculum_kkl"].log_.items() if key != "spent"
    }
    assert list(log) == [
        "constant",
        "sine 0.2-0.8 rad/s",
        "sine 0.8-2.5 rad/s",
        "square 2-10 s",
        "multi-sine",
    ]
    assert all(level["stopped"] in ("plateau", "cap", "diverged") for level in log.values())
    assert all(level["steps"] <= TINY["curriculum_steps"] for level in log.values())
    assert all(
        [error for step, error in level["validation_curve"] if step == level["best_step"]]
        == [min(error for _, error in level["validation_curve"])]
        for level in log.values()
    )


def test_auto_training_box_covers_forced_states_only_where_they_leave_the_unforced_range():
    config = Phase1Config(train_trajectories=8, train_box="auto")
    duffing = training_boxes(context_for(systems.get("duffing")(), TINY, None), config)
    assert len(duffing) == 2 and duffing[1][1][0] > 5  # forced Duffing reaches |x1| > 5
    lorenz = training_boxes(context_for(systems.get("lorenz")(), TINY, None), config)
    assert len(lorenz) == 1  # the attractor already spans the forced states
    with pytest.raises(ValueError, match="unknown train_box 'wide'; valid: auto, covering"):
        training_boxes(
            context_for(systems.get("lorenz")(), TINY, None),
            dataclasses.replace(config, train_box="wide"),
        )


def test_checkpoints_are_reused_and_invalidated(tmp_path, monkeypatch):
    calls = []
    original = optimize.minimize

    def counting(*args, **kwargs):
        calls.append(kwargs.get("description"))
        return original(*args, **kwargs)

    monkeypatch.setattr(autonomous, "minimize", counting)  # the encoder's training
    monkeypatch.setattr(decoder_module, "minimize", counting)  # the decoders' trainings
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
    fit_autonomous(context_for(system, {**TINY, "phase1_plateau_patience": 7}, tmp_path), config)
    assert len(calls) == 12  # and another plateau rule


def test_phase1_waits_its_own_patience_where_the_profile_sets_one(tmp_path):
    system = systems.get("vdp")()
    budget = {**TINY, "plateau_patience": 4, "plateau_reductions": 3}
    assert phase1_rule(context_for(system, budget, tmp_path)) == PlateauRule(
        validate_every=TINY["validate_every"], plateau_patience=4, plateau_reductions=3
    )
    longer = phase1_rule(context_for(system, {**budget, "phase1_plateau_patience": 9}, tmp_path))
    assert (longer.plateau_patience, longer.plateau_reductions) == (9, 3)


def test_fit_reports_count_the_optimizer_steps_and_samples_each_phase_spent(fitted_family):
    batch = 1024  # Phase1Config.batch; the encoder draws data pairs and collocation points
    selection = len(TINY["rate_candidates"]) * TINY["selection_steps"]
    logs = fitted_family["autonomous_kkl"].fit_report()["phase1_log"]
    encoder, decoder = logs["encoder"]["steps"], logs["decoder"]["steps"]
    assert encoder <= TINY["encoder_steps"] and decoder <= TINY["decoder_steps"]
    phase1 = {
        "steps": selection + encoder + decoder,
        "samples": batch * (selection + 2 * encoder + decoder),
    }

    def steps(name: str) -> int:  # the steps the trainings of a row's second phase took
        log = fitted_family[name].fit_report()["training_log"]
        if "steps" in log:  # one training
            return log["steps"]
        return sum(  # the curriculum's levels, the adaptation's rounds
            value["steps"]
            for key, value in log.items()
            if key != "spent" and isinstance(value, dict) and "steps" in value
        )

    curriculum, adaptation = steps("curriculum_kkl"), steps("injection_kkl")
    static, dynamic = steps("static_hyperkkl"), steps("dynamic_hyperkkl")
    second = {
        "autonomous_kkl": {"steps": 0, "samples": 0},
        "pure_injection_kkl": {"steps": 0, "samples": 0},
        "injection_kkl": {"steps": adaptation, "samples": adaptation * 1024},
        "static_hyperkkl": {"steps": static, "samples": static * 256},  # phase2_batch
        "dynamic_hyperkkl": {"steps": dynamic, "samples": dynamic * 256},  # 32 x 8 points
        "curriculum_kkl": {"steps": curriculum, "samples": curriculum * 1024},
    }
    for name, phase2 in second.items():
        spent = fitted_family[name].fit_report()["spent"]
        assert effort(spent) == {"phase1": phase1, "phase2": phase2}, name
        # the training's wall time is kept with the model (zero where nothing trained)
        assert spent["phase1"]["seconds"] > 0
        assert (spent["phase2"].get("seconds", 0) > 0) == (phase2["steps"] > 0), name


def effort(spent: dict) -> dict:
    """``spent`` without the wall times: the steps and samples of each phase."""
    return {phase: {"steps": s["steps"], "samples": s["samples"]} for phase, s in spent.items()}


def test_diagonal_latent_recursion_gives_the_numbers_of_the_matrix_product():
    a, b = latent_matrices(spread_eigenvalues(9, 1.0, 30.0), n_y=3)
    y = np.random.default_rng(0).normal(size=(4, 60, 3))

    def injection(k, z):
        return np.sin(z + k)

    diagonal = LatentObserver(a, b, 0.05)
    dense = LatentObserver(a, b, 0.05)
    dense._diagonal = False
    np.testing.assert_array_equal(diagonal.run(y, injection), dense.run(y, injection))
    z = torch.as_tensor(y[:, 0, :1].repeat(9, axis=1))
    assert torch.equal(latent_drift(z, torch.as_tensor(a)), z @ torch.as_tensor(a).T)
    assert np.array_equal(
        latent_drift(z.numpy(), a + np.eye(9, k=1)), z.numpy() @ (a + np.eye(9, k=1)).T
    )


def test_per_component_output_scaling_takes_the_elementwise_path_with_the_same_numbers():
    torch.manual_seed(0)
    x, z = torch.randn(200, 3), torch.randn(200, 6) * torch.arange(1.0, 7.0)
    network = NormalizedMLP(3, 6, 16, 2)
    network.set_normalization(x, z)  # outputs scaled per component: diagonal matrices
    with torch.no_grad():
        elementwise = network.forward_with_tangent(x, x.flip(0))
        network._diagonal_output = False  # force the matrix products
        dense = network.forward_with_tangent(x, x.flip(0))
    for fast, slow in zip(elementwise, dense, strict=True):
        torch.testing.assert_close(fast, slow, rtol=0, atol=1e-6)
    whitened = NormalizedMLP(3, 6, 16, 2)
    whitened.set_normalization(x, z + z[:, :1], whiten_outputs=True)
    network.load_state_dict(whitened.state_dict())  # now a full colouring: products again
    torch.testing.assert_close(network(x), whitened(x))
    assert network._diagonal_output is False


def test_wide_inputs_are_whitened_through_the_first_layer_with_the_same_result():
    torch.manual_seed(1)
    z = torch.randn(300, 40) @ torch.randn(40, 40)  # correlated: a full whitening
    x = torch.randn(300, 2)
    wide = NormalizedMLP(40, 2, 8, 2)  # 40 inputs > 8 hidden units: reassociated
    wide.set_normalization(z, x)
    with torch.no_grad():
        reference = wide.normalized(wide.input_difference(z - wide.in_mean))
        fast, tangent = wide.forward_with_tangent(z, z.flip(0))
        _, reference_tangent = torch.func.jvp(wide, (z,), (z.flip(0),))
    torch.testing.assert_close(wide(z), wide.out_mean + reference @ wide.out_coloring)
    torch.testing.assert_close(fast, wide(z))
    torch.testing.assert_close(tangent, reference_tangent)
