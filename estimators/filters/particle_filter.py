"""Particle filter on the exact discrete-time model: the suite's Bayes-optimal limit row.

The protocol's model is ``x_{k+1} = C(RK4(x_k, u_k) + w_k)``, ``w_k ~ N(0, q I)``,
``y_k = h(x_k) + v_k``, ``v_k ~ N(0, r I)``, with ``x_0`` uniform on the box
(``q = sigma_w^2``, ``r = sigma_v^2``). The posterior mean under this model is
the estimate with the least mean squared error any estimator can reach, and
a particle filter approximates it as closely as its particle count allows.

Proposal. The measurement noise (0.01) is as small as the process noise, so
the bootstrap filter (propose from the transition, weight by the likelihood)
puts almost all weight on a handful of particles each step and collapses.
The default therefore proposes from the *locally optimal* proposal
``p(s | x_k, y_{k+1})`` of the pre-constraint state ``s = RK4(x_k, u_k) + w_k``,
Gaussian when ``h`` is linear (as it is for every built-in system) and the
Gaussian of ``h`` linearised at the transition mean otherwise (Doucet,
Godsill and Andrieu, Statistics and Computing 2000). The importance weight
``p(y | C(s)) N(s; m, q I) / q(s)`` is exact for any ``h`` and ``C``; with a
linear ``h`` it reduces to ``N(y; h(m), q H H^T + r I)``. The first sample is
drawn from the box prior's Gaussian moments, inflated, updated by ``y_0``
and weighted by ``1_box(x) p(y_0 | x) / q(x)``. Systematic resampling runs
whenever the effective sample size drops below half the particles.

On a task with another measurement model (:mod:`kkl_bench.measurement`) the
weights use its exact log-density through its sensor (``system.h``); the
proposal linearises the sensor and takes the noise law's variance (plus a
quantizer's ``step^2 / 12``) as ``r``, which changes its efficiency, never the
weights' correctness. For the outlier law with one output the proposal is the
law's own mixture (:func:`mixture_proposal`, and :func:`initial_proposal` for
the first sample): one Gaussian proposal per component, weighted by how likely
the measurement is under each, so that an inlier measurement is not read with
the outliers' variance (with one Gaussian of the law's variance, 10000
particles did not reach the limit: a recurrent network beat it on two outlier
cells), nor an outlier with the inliers' (a first measurement 40 away from
the state, read with one Gaussian of the law's variance, put every particle
outside the x0 box: the trajectory was lost from its first sample). A sample whose measurement is missing (NaN) moves the
particles by the transition and leaves the weights as they are. The first
sample is always measured (protocol 7.6).

Every trajectory draws from its own generator, keyed by the seed and its
first measurement, so estimates are causal, batch-independent and
reproducible. Work is vectorised over particles and trajectories, in chunks
of trajectories that bound the memory (the reference engine's) and keep both engines'
draws the same. The compiled engine (``engine='compiled'``, the default) runs each
trajectory from its second sample on in one numba kernel
(:mod:`kkl_bench.estimators.filters.particle_kernels`) on the same draws; the first
sample's proposal is the reference engine's numpy code for both.
"""

from __future__ import annotations

import math

import numpy as np
from kkl_bench.estimators.filters import particle_kernels
from kkl_bench.estimators.filters.kalman import TwoEngines, box_prior, check_engine
from kkl_bench.estimators.filters.monte_carlo import trajectory_generators
from kkl_bench.estimators.filters.particle_proposals import (
    initial_proposal,
    mixture_proposal,
    optimal_proposal,
    systematic_resample,
)
from scipy.special import logsumexp

from kkl_bench.estimator import Estimator
from kkl_bench.fitting.calibration import CalibratesOnLoggedData
from kkl_bench.protocol.simulate import rk4_step
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators
from kkl_bench.support.kernel_cache import bind_once

PROPOSALS = ("optimal", "bootstrap")

_CHUNK_ELEMENTS = 2**24
"""Upper bound on trajectories x particles x n_y x n_x per chunk (~128 MB of float64)."""

_PRIOR_INFLATION = 2.0
"""The initial proposal's prior covariance is the box's, times this (heavier than the box)."""

LARGEST_STATE = 10
"""The largest state dimension the filter is run for (protocol 6.1: Lorenz-96 with 10 states)."""


@estimators.register("particle_filter")
class ParticleFilter(TwoEngines, CalibratesOnLoggedData, Estimator):
    """Particle filter with the locally optimal proposal (see the module doc).

    Parameters
    ----------
    n: particles per trajectory.
    proposal: ``"optimal"`` (default) or ``"bootstrap"`` (the transition; for comparison).
    resample_below: resample when the effective sample size falls below this fraction of ``n``.
    engine: ``"compiled"`` (the default, the published cells' since issue 65): one numba
        kernel a trajectory over the system's compiled model, drawing the reference
        engine's random numbers (:mod:`kkl_bench.estimators.filters.particle_kernels`); a
        system without a compiled model runs the reference engine. ``"reference"``: numpy,
        vectorised over particles and trajectories, what the kernel is checked against.
    """

    name = "particle_filter"
    family = "limit"
    supported_measurements = frozenset({"sensor", "sampling", "noise"})
    bayes_limit = True

    def __init__(
        self,
        n: int = 10000,
        proposal: str = "optimal",
        resample_below: float = 0.5,
        engine: str = "compiled",
    ) -> None:
        self.n = n
        self.proposal = proposal
        self.resample_below = resample_below
        self.engine = engine
        check_engine("particle_filter", engine)
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"particle_filter: n={n!r} must be a positive integer")
        if proposal not in PROPOSALS:
            raise ValueError(
                f"particle_filter: proposal={proposal!r}; valid: {', '.join(PROPOSALS)}"
            )
        if not 0.0 <= resample_below <= 1.0:
            raise ValueError(
                f"particle_filter: resample_below={resample_below!r} must be in [0, 1]"
            )

    def unsupported_reason(self, system, measurement):
        if system.n_x > LARGEST_STATE:
            return (
                f"not affordable here, and no limit: {system.name} has {system.n_x} states, "
                f"beyond the {LARGEST_STATE} the filter is run for (a trajectory-step costs "
                "about 128 ms at 40 states, and the particles a particle filter needs grow "
                "exponentially with the state dimension; protocol 6.1)"
            )
        return super().unsupported_reason(system, measurement)

    def fit(self, context):
        super().fit(context)
        self.model_ = self.check_fitted().system.compiled() if self.engine == "compiled" else None
        return self

    def fit_report(self):
        return {
            **super().fit_report(),
            "particles": self.n,
            "proposal": self.proposal,
            "engine": self.engine_used,
        }

    def flops_per_step(self) -> float:
        """Flops of one trajectory-step: per particle, the RK4 step, the proposal's mean
        (``2 n m + m``), its draw and density (``3 n^2 + n``), the weight, and resampling
        (about 13 more); NaN for a system without a compiled model."""
        model = self.check_fitted().system.compiled()
        if model is None:
            return math.nan
        n, m = model.n_x, model.n_y
        return float(self.n * (model.step_flops + 2 * n * m + m + 3 * n * n + n + 13))

    def operations_per_step(self) -> dict[str, float]:
        """What one trajectory-step must draw and evaluate besides its flops (protocol 6.3):
        per particle, ``n_x`` standard normal numbers for the process and, with the optimal
        proposal, ``n_y`` for the measurement, a uniform number to pick a mixture's
        component, and the transcendental functions: the weight's ``exp``, the noise law's
        log-density (``log1p`` an output for Student's t; ``exp`` and ``log1p`` for the
        outlier mixture) and a mixture proposal's ``2 c + 2`` (its components' ``exp``
        twice and two ``log``); and one uniform number, the resampling offset."""
        context = self.check_fitted()
        system, measurement = context.system, context.measurement
        mixture = measurement.mixture if system.n_y == 1 else None
        optimal = self.proposal == "optimal"
        components = len(mixture) if mixture and optimal else 1
        law = {"student-t": 1, "outliers": 2}.get(measurement.noise.law, 0)
        proposal = 2 * components + 2 if components > 1 else 0
        return {
            "normal": self.n * (system.n_x + (system.n_y if optimal else 0)),
            "uniform": self.n * (components > 1) + 1,
            "transcendental": self.n * (1 + law * system.n_y + proposal),
        }

    def estimate(self, t, y, u):
        context = self.check_fitted()
        system = context.system
        dt = float(t[1] - t[0]) if len(t) > 1 else context.dt
        batch = y.shape[0]
        per_trajectory = self.n * system.n_y * system.n_x
        chunk = max(1, _CHUNK_ELEMENTS // per_trajectory)
        x_hat = np.full((batch, y.shape[1], system.n_x), np.nan)
        for start in range(0, batch, chunk):
            rows = slice(start, start + chunk)
            x_hat[rows] = self._filter(system, dt, y[rows], u[rows])
        return x_hat

    def _filter(self, system: System, dt: float, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Posterior means ``(batch, steps, n_x)`` for ``y: (batch, steps, n_y)``, ``u: (batch, steps, 1)``."""
        context = self.check_fitted()
        measurement = context.measurement
        mixture = measurement.mixture if system.n_y == 1 else None  # one output only
        generators = trajectory_generators(context.seed, y[:, 0])

        def normals(dim):  # (batch, n, dim), each trajectory from its own generator
            return np.stack([rng.standard_normal((self.n, dim)) for rng in generators])

        def uniforms():  # (batch, n)
            return np.stack([rng.random(self.n) for rng in generators])

        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            particles, log_weights = self._initial(
                system, y[:, 0], mixture or ((1.0, measurement.variance),), normals, uniforms
            )
            run = self._run_reference if self.model_ is None else self._run_compiled
            x_hat = run(particles, log_weights, y, u, dt, mixture, generators, normals, uniforms)
        # a trajectory whose weights all vanished (or overflowed) stays NaN from then on
        return np.where(
            np.isnan(x_hat).any(axis=-1, keepdims=True).cumsum(axis=1) > 0, np.nan, x_hat
        )

    def _run_reference(self, particles, log_weights, y, u, dt, mixture, generators, normals, uniforms):  # fmt: skip
        """The estimates ``(batch, steps, n_x)`` from the first sample's ``particles (batch,
        n, n_x)`` and ``log_weights (batch, n)`` on, in numpy (:meth:`_step_reference`)."""
        batch, steps, _ = y.shape
        x_hat = np.full((batch, steps, particles.shape[-1]), np.nan)
        for k in range(steps):
            if k > 0:
                particles, log_weights = self._step_reference(
                    particles, log_weights, u[:, k - 1, 0], y[:, k], dt, mixture, normals, uniforms
                )
            log_weights = log_weights - logsumexp(log_weights, axis=1, keepdims=True)
            weights = np.exp(log_weights)
            x_hat[:, k] = np.einsum("bn,bnx->bx", weights, particles)
            if k + 1 < steps:
                particles, log_weights = self._resample(particles, log_weights, weights, generators)
        return x_hat

    def _run_compiled(self, particles, log_weights, y, u, dt, mixture, generators, normals, uniforms):  # fmt: skip
        """:meth:`_run_reference` by the compiled kernel, one call a trajectory
        (:func:`~kkl_bench.estimators.filters.particle_kernels.filter_trajectory`), which draws
        from each trajectory's generator the numbers the reference engine draws."""
        context = self.check_fitted()
        model, measurement = self.model_, context.measurement
        batch, steps, _ = y.shape
        present = np.isfinite(y).all(axis=-1)  # (batch, steps)
        proposing = np.full(steps, self.proposal == "optimal") & present.any(axis=0)
        all_present = present.all(axis=0)
        components = np.array(mixture or ((1.0, measurement.variance),), dtype=np.float64)
        law, constants = particle_kernels.noise_law_constants(measurement.noise)
        y, u = self.kernel_inputs(y, u)
        x_hat = np.full((batch, steps, model.n_x), np.nan)
        run = bind_once(
            particle_kernels.filter_trajectory, model.drift, model.output,
            model.output_jacobian, model.sense, model.sense_slope, model.constrain,
        )  # fmt: skip
        for b, rng in enumerate(generators):
            run(
                model.p, model.q, model.s, model.g, rng,
                np.ascontiguousarray(particles[b].T, dtype=np.float64),
                np.ascontiguousarray(log_weights[b], dtype=np.float64), u[b], dt, y[b],
                present[b], proposing, all_present, float(context.sigma_w**2),
                components, model.constant_output_jacobian, law, constants,
                float(self.resample_below), x_hat[b],
            )  # fmt: skip
        return x_hat

    def _step_reference(self, particles, log_weights, u, y, dt, mixture, normals, uniforms):
        """``(particles, log_weights)`` one step on: every particle moved (transition, or
        the proposal where measured) and reweighted by its measurement ``y: (batch, n_y)``
        (NaN where absent), ``u: (batch,)`` held over the step; ``mixture`` the noise law's
        components for the proposal (None for one Gaussian); ``normals(dim)`` and
        ``uniforms()`` each trajectory's draws (numpy)."""
        context = self.check_fitted()
        system, measurement = context.system, context.measurement
        q, r = context.sigma_w**2, measurement.variance
        batch = y.shape[0]
        mean = rk4_step(system, particles, np.broadcast_to(u[:, None], (batch, self.n)), dt)
        observed = y[:, None, :]
        present = np.isfinite(y).all(axis=-1)[:, None]  # (batch, 1)
        if self.proposal == "optimal" and present.any():
            arguments = (system, mean, np.where(present[..., None], observed, 0.0), q)
            if mixture is None:
                sample, log_ratio = optimal_proposal(
                    *arguments, r, normals(system.n_x), normals(system.n_y)
                )
            else:
                sample, log_ratio = mixture_proposal(
                    *arguments, mixture, normals(system.n_x), normals(system.n_y), uniforms()
                )
            if not present.all():  # (draws only then: the stream stays v1's)
                transition = mean + np.sqrt(q) * normals(system.n_x)
                sample = np.where(present[..., None], sample, transition)
                log_ratio = np.where(present, log_ratio, 0.0)
        else:
            sample, log_ratio = mean + np.sqrt(q) * normals(system.n_x), 0.0
        particles = system.constrain(sample)
        log_likelihood = measurement.log_density(observed, system.h(particles))
        log_likelihood = np.where(present, log_likelihood, 0.0)
        return particles, log_weights + log_likelihood - log_ratio

    def _initial(self, system: System, y0: np.ndarray, components, normals, uniforms):
        """Particles ``(batch, n, n_x)`` and log weights ``(batch, n)`` for the first sample
        (``normals(dim)``, ``uniforms()``: each trajectory's draws ``(batch, n, dim)``,
        ``(batch, n)``).

        Proposal: :func:`initial_proposal` from the box's Gaussian moments (covariance
        inflated), ``h`` linearised at the box centre and the noise law's ``components``
        (``((1, r),)`` unless the law is a mixture); weight ``1_box p(y0 | x) / q(x)``.
        """
        context = self.check_fitted()
        centre, covariance = box_prior(context)
        particles, log_proposal = initial_proposal(
            centre,
            _PRIOR_INFLATION * covariance,
            system.h_jacobian(centre),
            y0 - system.h(centre),
            components,
            normals(system.n_x),
            uniforms() if len(components) > 1 else None,
        )
        inside = np.all((particles >= context.x0_low) & (particles <= context.x0_high), axis=-1)
        log_likelihood = context.measurement.log_density(y0[:, None, :], system.h(particles))
        return particles, np.where(inside, log_likelihood - log_proposal, -np.inf)

    def _resample(self, particles, log_weights, weights, generators):
        """Systematic resampling of the trajectories whose effective sample size is low
        (``weights = exp(log_weights)``, normalised, ``(batch, n)``)."""
        effective = 1.0 / np.sum(weights**2, axis=1)
        offsets = np.array([rng.random() for rng in generators])
        low = effective < self.resample_below * self.n
        if not low.any():
            return particles, log_weights
        ancestors = systematic_resample(np.nan_to_num(weights[low]), offsets[low])
        particles = particles.copy()
        log_weights = log_weights.copy()
        particles[low] = np.take_along_axis(particles[low], ancestors[..., None], axis=1)
        log_weights[low] = -np.log(self.n)
        return particles, log_weights
