"""The particle filter against known answers: resampling counts, the optimal proposal's
weights, the Kalman filter on a linear system, and convergence in the particle count."""

import numba
import numpy as np
import pytest
from kkl_bench.estimators.filters.kalman import box_prior
from kkl_bench.estimators.filters.particle_filter import PROPOSALS, ParticleFilter
from kkl_bench.estimators.filters.particle_proposals import (
    gaussian_log_density,
    optimal_proposal,
    systematic_resample,
)

from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol.simulate import rk4_step, rk4_step_jacobian
from kkl_bench.registry import regimes, systems
from kkl_bench.testing import Conformance
from tests.test_kkl import HarmonicOscillator, context_for


def test_systematic_resampling_copies_each_particle_floor_or_ceil_of_n_w_times():
    weights = np.array([[0.5, 0.25, 0.125, 0.125], [0.0, 1.0, 0.0, 0.0], [0.1, 0.2, 0.3, 0.4]])
    for offset in (0.0, 0.3, 0.999):
        ancestors = systematic_resample(weights, np.full(3, offset))
        counts = np.stack([np.bincount(row, minlength=4) for row in ancestors])
        assert np.all(counts >= np.floor(4 * weights)) and np.all(counts <= np.ceil(4 * weights))
        assert np.all(np.diff(ancestors, axis=1) >= 0)
    assert systematic_resample(weights, np.zeros(3))[1].tolist() == [1, 1, 1, 1]


def test_a_trajectorys_ancestors_do_not_depend_on_the_other_rows():
    # equal weights put a position exactly on a cumulative weight (0.3 against 0.1 + 0.1 +
    # 0.1); a search over all rows at once, row b shifted by b, rounded the tie differently
    # in each row
    ancestors = systematic_resample(np.full((4, 10), 0.1), np.zeros(4))
    assert (ancestors == ancestors[0]).all()
    assert ancestors[0].tolist() == [0, 1, 2, 2, 4, 5, 6, 7, 8, 9]


def test_the_compiled_kernels_draw_numpys_numbers_from_a_generator():
    """The compiled filters draw inside the kernel from each trajectory's generator: numba
    must give the numbers numpy gives, and leave the generator where numpy would."""

    @numba.njit
    def draw(rng, normals, uniforms):
        for i in range(normals.shape[0]):
            normals[i] = rng.standard_normal()
        for i in range(uniforms.shape[0]):
            uniforms[i] = rng.random()

    inside, outside = np.random.default_rng(7), np.random.default_rng(7)
    normals, uniforms = np.empty(1000), np.empty(10)
    draw(inside, normals, uniforms)
    assert np.array_equal(normals, outside.standard_normal(1000))
    assert np.array_equal(uniforms, outside.random(10))
    assert inside.random() == outside.random()


def test_optimal_proposal_weights_of_a_linear_output_are_the_predictive_likelihood():
    """With ``h`` linear the weight ``p(y|s) N(s; m, qI) / q(s)`` does not depend on the
    sample and equals ``N(y; h(m), q H H^T + r I)``."""
    system = systems.get("lorenz96-n5")()  # three outputs
    rng = np.random.default_rng(0)
    q, r = 0.01**2, 0.02**2
    mean = rng.uniform(-5, 5, (7, system.n_x))
    y = system.h(mean) + rng.normal(0, 0.05, (7, system.n_y))
    w, v = rng.standard_normal((7, system.n_x)), rng.standard_normal((7, system.n_y))
    sample, log_ratio = optimal_proposal(system, mean, y, q, r, w, v)
    log_weight = gaussian_log_density(y - system.h(sample), r) - log_ratio
    # H H^T = I for a selection of states, so S = (q + r) I
    assert np.allclose(log_weight, gaussian_log_density(y - system.h(mean), q + r), atol=1e-9)


def test_optimal_proposal_samples_the_conditional_gaussian():
    system = HarmonicOscillator()
    q, r, draws = 0.1**2, 0.05**2, 200_000
    rng = np.random.default_rng(1)
    mean = np.broadcast_to(np.array([0.3, -0.2]), (draws, 2))
    y = np.full((draws, 1), 0.5)
    sample, _ = optimal_proposal(
        system, mean, y, q, r, rng.standard_normal((draws, 2)), rng.standard_normal((draws, 1))
    )
    # x1 | y: precision 1/q + 1/r; x2 is untouched by y
    variance = 1 / (1 / q + 1 / r)
    assert sample[:, 0].mean() == pytest.approx(variance * (0.3 / q + 0.5 / r), abs=2e-4)
    assert sample[:, 0].var() == pytest.approx(variance, rel=0.02)
    assert sample[:, 1].mean() == pytest.approx(-0.2, abs=1e-3)
    assert sample[:, 1].var() == pytest.approx(q, rel=0.02)


def kalman_filter(context, data):
    """The exact posterior means ``(batch, steps, n_x)`` of ``data`` under the linear system
    ``context.system`` with the Gaussian moments of its x0 box as prior."""
    system, dt = context.system, context.dt
    q, r = context.sigma_w**2, context.sigma_v**2
    transition = rk4_step_jacobian(system, np.zeros(system.n_x), np.zeros(()), dt)
    output = system.h_jacobian(np.zeros(system.n_x))
    mean, covariance = box_prior(context)
    batch, steps, _ = data.y.shape
    means = np.empty((batch, steps, system.n_x))
    for b in range(batch):
        m, p = mean.copy(), covariance.copy()
        for k in range(steps):
            if k:
                m = rk4_step(system, m, np.asarray(data.u[b, k - 1, 0]), dt)
                p = transition @ p @ transition.T + q * np.eye(system.n_x)
            gain = p @ output.T / (output @ p @ output.T + r)
            m = m + gain @ (data.y[b, k] - output @ m)
            p = p - gain @ output @ p
            means[b, k] = m
    return means


@pytest.fixture(scope="module")
def linear_case(tmp_path_factory):
    """Harmonic-oscillator trajectories, their fit context and exact Kalman posterior means."""
    context = context_for(HarmonicOscillator(), {}, tmp_path_factory.mktemp("cache"))
    data = context.training.simulate(regimes.get("sinusoid")(), 3, stream="pf", n_samples=160)
    return context, data, kalman_filter(context, data)


def late_rms(error):
    """RMS over the samples after the box prior is forgotten (k >= 80)."""
    return np.sqrt(np.mean(error[:, 80:] ** 2))


def test_particle_filter_reaches_the_kalman_filter_on_a_linear_system(linear_case):
    """Uniform and Gaussian priors give the same posterior once the data dominate."""
    context, data, exact = linear_case
    x_hat = ParticleFilter(n=4000).fit(context).estimate(data.t, data.y, data.u)
    # the Kalman filter's error (~0.037) is the posterior's spread; the particle
    # filter differs from it by Monte Carlo error only (~0.0014 at 4000 particles)
    assert late_rms(x_hat - exact) < 0.1 * late_rms(exact - data.x)


def test_optimal_proposal_has_less_monte_carlo_error_than_the_bootstrap(linear_case):
    context, data, exact = linear_case
    distance = {
        proposal: late_rms(
            ParticleFilter(n=100, proposal=proposal).fit(context).estimate(data.t, data.y, data.u)
            - exact
        )
        for proposal in PROPOSALS
    }
    assert distance["optimal"] < 0.75 * distance["bootstrap"]


def test_particle_filter_error_falls_as_particles_grow():
    """Distance to a 40000-particle reference on one cell's trajectories shrinks with n."""
    check = Conformance("particle_filter", system="duffing")
    data = check.data
    steps = slice(0, 120)

    def run(n):
        estimator = ParticleFilter(n=n).fit(check.context)
        return estimator.estimate(data.t[steps], data.y[:, steps], data.u[:, steps])

    reference = run(40000)
    errors = [np.sqrt(np.mean((run(n) - reference) ** 2)) for n in (30, 300, 3000)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.3 * errors[0]


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"n": 0}, "n=0 must be a positive integer"),
        ({"proposal": "prior"}, "proposal='prior'; valid: optimal, bootstrap"),
        ({"resample_below": 2.0}, "resample_below=2.0 must be in"),
    ],
)
def test_bad_parameters_are_named(params, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ParticleFilter(**params)


def test_the_mixture_proposal_is_the_optimal_one_for_outlier_noise():
    """With a linear output, the optimal proposal makes the incremental weight
    p(y | s) N(s; m, q) / q(s) the same for every draw: p(y | x), the mixture of the
    components' Gaussian marginals."""
    from kkl_bench.estimators.filters.particle_proposals import mixture_proposal, optimal_proposal

    from kkl_bench.measurement import NoiseLaw

    system = systems.get("duffing")()
    law = NoiseLaw("outliers", 0.05, outlier_fraction=0.1, outlier_scale=30.0)
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(500, 2))
    y = np.full((500, 1), 0.4)
    q = 1e-4
    w, v, uniform = rng.normal(size=(500, 2)), rng.normal(size=(500, 1)), rng.random(500)
    sample, log_ratio = mixture_proposal(system, mean, y, q, law.mixture, w, v, uniform)
    increment = law.log_density(y - system.h(sample)) - log_ratio
    e = (y - system.h(mean))[:, 0]
    expected = np.logaddexp(
        *(
            np.log(weight) - 0.5 * (e**2 / (q + r) + np.log(2 * np.pi * (q + r)))
            for weight, r in law.mixture
        )
    )
    assert np.allclose(increment, expected, rtol=0, atol=1e-9)
    one = mixture_proposal(system, mean, y, q, ((1.0, 0.0025),), w, v, uniform)
    assert all(
        np.allclose(a, b, rtol=1e-12, atol=1e-12)
        for a, b in zip(one, optimal_proposal(system, mean, y, q, 0.0025, w, v), strict=True)
    )


def test_the_initial_proposal_is_the_posterior_for_a_linear_output():
    """With a linear output, the first sample's proposal is the exact posterior of the
    Gaussian prior: the weight p(y0 | x) N(x; m, P) / q(x) is the same for every particle
    (the mixture of the components' predictive densities), whichever component an
    outlier-law draw took; one component is the Kalman update."""
    from kkl_bench.estimators.filters.particle_proposals import initial_proposal

    from kkl_bench.measurement import NoiseLaw

    system = systems.get("duffing")()
    law = NoiseLaw("outliers", 0.05, outlier_fraction=0.1, outlier_scale=30.0)
    mean, covariance = np.array([0.2, -0.1]), np.diag([0.4, 0.3])
    jacobian = system.h_jacobian(mean)
    y0 = np.array([[0.5], [2.5]])  # an inlier and an outlier
    rng = np.random.default_rng(0)
    standard, uniform = rng.normal(size=(2, 400, 2)), rng.random((2, 400))
    innovation = y0 - system.h(mean)
    particles, log_q = initial_proposal(
        mean, covariance, jacobian, innovation, law.mixture, standard, uniform
    )
    offset = particles - mean
    log_prior = -0.5 * np.sum(offset**2 / np.diag(covariance), axis=-1)
    log_weight = law.log_density(y0[:, None, :] - system.h(particles)) + log_prior - log_q
    assert np.ptp(log_weight, axis=1) == pytest.approx([0, 0], abs=1e-9)
    # x1's mean is the components' Kalman means weighted by w_c N(e; 0, P11 + r_c)
    e = innovation[:, 0]
    log_w = np.stack(
        [np.log(w) - 0.5 * (e**2 / (0.4 + r) + np.log(0.4 + r)) for w, r in law.mixture], -1
    )
    posterior = np.exp(log_w - np.logaddexp(*log_w.T)[:, None])
    kalman = np.stack([mean[0] + 0.4 / (0.4 + r) * e for _, r in law.mixture], -1)
    assert particles[:, :, 0].mean(axis=1) == pytest.approx(
        np.sum(posterior * kalman, axis=1), abs=0.05
    )
    one, _ = initial_proposal(
        mean, covariance, jacobian, innovation, ((1.0, 0.0025),), standard, None
    )
    gain = 0.4 / (0.4 + 0.0025)
    assert one[:, :, 0].mean(axis=1) == pytest.approx(mean[0] + gain * innovation[:, 0], abs=0.01)
    assert one[:, :, 0].var(axis=1) == pytest.approx([0.4 * (1 - gain)] * 2, rel=0.2)


def test_lorenz96_beyond_ten_states_is_unsupported_with_the_reason():
    pf = ParticleFilter()
    assert pf.unsupported_reason(systems.get("lorenz96-n10")(), MeasurementModel()) is None
    reason = pf.unsupported_reason(systems.get("lorenz96-n20")(), MeasurementModel())
    assert "20 states" in reason and "protocol 6.1" in reason
