"""The particle filter's transition and weighting compiled: one step of every particle.

:func:`propagate` does, for each trajectory and particle, what
:meth:`kkl_bench.estimators.filters.particle_filter.ParticleFilter._filter` does in numpy between
two estimates: the RK4 transition mean, the draw from the (locally optimal, or the noise
law's mixture of) proposal, the constraint, and the importance weight with the noise
law's exact log-density, in the same operations and order, on the same standard normal
and uniform numbers (drawn by the caller from each trajectory's generator, as the
reference engine draws them). Normalising the weights, the estimate and resampling stay
the reference engine's numpy code, so the compiled engine's estimates equal the
reference's to rounding (``tests/test_filter_engines.py``).

Shapes: ``particles: (batch, n, n_x)`` and ``log_weights: (batch, n)``, updated in place;
``u: (batch,)`` the input held over the step; ``y: (batch, n_y)`` the measurements
(read where ``present: (batch,)``); ``components: (c, 2)`` the proposal's Gaussian
components ``(weight, variance)`` (one row unless the noise law is a mixture);
``w: (batch, n, n_x)``, ``v: (batch, n, n_y)``, ``uniform: (batch, n)`` and
``transition: (batch, n, n_x)`` standard normal and uniform draws (empty where a step
draws none).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from kkl_bench.estimators.filters.kalman_kernels import _sensed_output_jacobian
from kkl_bench.estimators.filters.kalman_linalg import invert, upper_cholesky

from kkl_bench.protocol.compiled import matrix_column, rk4_step, sensed_output

GAUSSIAN, STUDENT_T, OUTLIERS = 0, 1, 2
"""The noise laws' codes in :func:`log_likelihood` (:class:`kkl_bench.measurement.NoiseLaw`)."""
LOG_2PI = math.log(2 * math.pi)


def noise_law_constants(noise) -> tuple[int, np.ndarray]:
    """``(code, constants)`` of a :class:`~kkl_bench.measurement.NoiseLaw` for
    :func:`log_likelihood`, computed as its numpy ``log_density`` computes them."""
    if noise.law == "student-t":
        return STUDENT_T, np.array([noise.sigma, noise.dof, noise.student_t_log_norm])
    if noise.law == "outliers":
        p, s = noise.outlier_fraction, noise.outlier_scale
        log_outlier = math.log(p) - math.log(s) if p > 0 else -math.inf
        log_sigma = math.log(noise.sigma)
        return OUTLIERS, np.array(
            [noise.sigma, s, math.log1p(-p), log_outlier, 0.5 * LOG_2PI, log_sigma]
        )
    return GAUSSIAN, np.array([noise.sigma**2])


@numba.njit(cache=True, error_model="numpy")
def _logaddexp(a, b):
    """numpy's ``logaddexp``."""
    if a == b:
        return a + math.log(2.0)
    difference = a - b
    if difference > 0:
        return a + math.log1p(math.exp(-difference))
    if difference <= 0:
        return b + math.log1p(math.exp(difference))
    return difference  # NaN


@numba.njit(cache=True, error_model="numpy")
def log_likelihood(residual, law, constants, gaussian_norm):
    """``log p(residual)`` of the noise law ``law`` (:func:`noise_law_constants`), summed over
    the outputs, in the operations of :meth:`kkl_bench.measurement.NoiseLaw.log_density`
    (``gaussian_norm = n_y log(2 pi variance)`` for the Gaussian law)."""
    if law == GAUSSIAN:
        total = 0.0
        for j in range(residual.shape[0]):
            total += residual[j] ** 2
        return -0.5 * (total / constants[0] + gaussian_norm)
    total = 0.0
    for j in range(residual.shape[0]):
        z = residual[j] / constants[0]
        if law == STUDENT_T:
            nu = constants[1]
            total += constants[2] - (nu + 1) / 2 * math.log1p(z**2 / nu)
        else:
            scale = constants[1]
            inlier = constants[2] - 0.5 * z**2
            outlier = constants[3] - 0.5 * (z / scale) ** 2
            total += _logaddexp(inlier, outlier) - constants[4] - constants[5]
    return total


@numba.njit(cache=True, error_model="numpy")
def _log_det(matrix, work):
    """``log det`` of a symmetric positive definite ``matrix`` (its Cholesky factor into
    ``work``); NaN if it is not positive definite (a NaN on the factor's diagonal)."""
    upper_cholesky(matrix_column(matrix), matrix_column(work))
    total = 0.0
    for j in range(matrix.shape[0]):
        total += 2.0 * math.log(work[j, j])
    return total


@numba.njit(cache=True, error_model="numpy")
def _logsumexp(values):
    """``log sum exp(values)`` (scipy's ``logsumexp`` of a one-dimensional array)."""
    largest = -math.inf
    for value in values:
        largest = max(largest, value)
    if not math.isfinite(largest):
        largest = 0.0
    total = 0.0
    for value in values:
        total += math.exp(value - largest)
    return math.log(total) + largest


@numba.njit(cache=True, error_model="numpy")
def _proposal_covariances(H, q, components, S, inverse, gain, log_det, log_det_precision, work):
    """What each component's optimal proposal (``_GaussianProposal``) takes from ``H``
    alone: ``S = q H H^T + r I``, its ``inverse``, ``gain = q H^T S^-1``, ``log det S`` and
    ``log det S - n log q - n_y log r`` (``log_det_precision``); False if an ``S`` is
    singular."""
    n_y, n = H.shape
    for c in range(components.shape[0]):
        r = components[c, 1]
        for i in range(n_y):
            for j in range(n_y):
                total = 0.0
                for m in range(n):
                    total += q * H[i, m] * H[j, m]
                S[c, i, j] = total + (r if i == j else 0.0)
        if not invert(S[c], inverse[c]):
            return False
        for i in range(n):
            for j in range(n_y):
                total = 0.0
                for m in range(n_y):
                    total += q * H[m, i] * inverse[c, m, j]
                gain[c, i, j] = total
        log_det[c] = _log_det(S[c], work)
        log_det_precision[c] = log_det[c] - n * math.log(q) - n_y * math.log(r)
    return True


@numba.njit(cache=True, error_model="numpy")
def _draw(mean, H, gain, innovation, root_q, root_r, w, v, out, process):
    """Matheron's rule: ``out = mean + sqrt(q) w + gain (e - H sqrt(q) w - sqrt(r) v)``."""
    n_y, n = H.shape
    for i in range(n):
        process[i] = root_q * w[i]
    for i in range(n):
        out[i] = mean[i] + process[i]
    for i in range(n):
        correction = 0.0
        for j in range(n_y):
            along = 0.0
            for m in range(n):
                along += H[j, m] * process[m]
            correction += gain[i, j] * (innovation[j] - along - root_r * v[j])
        out[i] = out[i] + correction


@numba.njit(cache=True, error_model="numpy")
def _proposal_log_density(sample, mean, gain, innovation, H, q, r, log_det_precision, norm, offset):
    """``log q(sample)`` of one Gaussian proposal, whose mean is ``mean + gain e``
    (``_GaussianProposal.log_density``; ``norm = n log(2 pi)``; ``offset: (n,)`` scratch)."""
    n_y, n = H.shape
    offset_sum = 0.0
    for i in range(n):
        correction = 0.0
        for j in range(n_y):
            correction += gain[i, j] * innovation[j]
        offset[i] = sample[i] - (mean[i] + correction)
        offset_sum += offset[i] ** 2
    projected_sum = 0.0
    for j in range(n_y):
        along = 0.0
        for i in range(n):
            along += H[j, i] * offset[i]
        projected_sum += along**2
    quadratic = offset_sum / q + projected_sum / r
    return 0.5 * (log_det_precision - quadratic - norm)


@numba.njit(error_model="numpy")  # disk-cached once bound to a model: kernel_cache.bind
def propagate(
    drift, output, output_jacobian, sense, sense_slope, constrain, p, q_output, s, g,
    particles, log_weights, u, dt, y, present, q, components, proposing, law, constants,
    w, v, uniform, transition,
):  # fmt: skip
    """Move every particle one step and update its log weight (the module docstring).

    A present trajectory, when ``proposing`` (the optimal proposal on a step with some
    measurement), draws from the proposal; an absent one then moves by the transition
    with ``transition``'s draws, and without ``proposing`` every trajectory moves by the
    transition with ``w``'s. The weight gains ``log p(y | x) - log(q(s) / N(s; mean, q I))``
    where the trajectory is measured. What depends on the sensor's Jacobian ``H`` alone
    is computed again only when ``H`` changes (never, for a linear sensor).

    The model's functions sweep over one trajectory's particles at a time (``(n_x, n)``:
    the transition means, their outputs and Jacobians, the constraint and the moved
    particles' outputs); the proposal draws and weights go particle by particle."""
    batch, n_particles, n = particles.shape
    n_y, count = y.shape[1], components.shape[0]
    points, means = np.empty((n, n_particles)), np.empty((n, n_particles))
    moved, work = np.empty((n, n_particles)), np.empty((5, n, n_particles))
    u_points, log_ratios = np.empty(n_particles), np.empty(n_particles)
    outputs, slopes = np.empty((n_y, n_particles)), np.empty((n_y, n_particles))
    jacobians = np.empty((n_y, n, n_particles if proposing else 0))
    mean, sample, process = np.empty(n), np.empty(n), np.empty(n)
    H, H_used = np.empty((n_y, n)), np.full((n_y, n), np.nan)
    innovation = np.empty(n_y)
    S, inverse = np.empty((count, n_y, n_y)), np.empty((count, n_y, n_y))
    cholesky_work, gain = np.empty((n_y, n_y)), np.empty((count, n, n_y))
    log_det, log_det_precision, log_mixture = np.empty(count), np.empty(count), np.empty(count)
    draws, densities = np.empty((count, n)), np.empty(count)
    singular = False
    root_q = math.sqrt(q)
    root_r = np.sqrt(components[:, 1])
    log_component_weights = np.log(components[:, 0])
    n_log_2pi, n_y_log_2pi = n * math.log(2 * math.pi), n_y * math.log(2 * math.pi)
    transition_norm = n * math.log(2 * math.pi * q)
    gaussian_norm = n_y * math.log(2 * math.pi * constants[0]) if law == GAUSSIAN else 0.0
    for b in range(batch):
        measured = present[b]
        drawing = proposing and measured
        for i in range(n_particles):
            for k in range(n):
                points[k, i] = particles[b, i, k]
        u_points[:] = u[b]
        rk4_step(drift, p, g, points, u_points, dt, means, work)
        if drawing:
            _sensed_output_jacobian(output, output_jacobian, sense_slope, q_output, s, means, outputs, slopes, jacobians)  # fmt: skip
            sensed_output(output, sense, q_output, s, means, outputs)
        for i in range(n_particles):
            for k in range(n):
                mean[k] = means[k, i]
            log_ratio = 0.0
            if drawing:
                changed = False
                for j in range(n_y):
                    for k in range(n):
                        H[j, k] = jacobians[j, k, i]
                        changed = changed or H[j, k] != H_used[j, k]
                if changed:
                    H_used[:, :] = H
                    singular = not _proposal_covariances(
                        H, q, components, S, inverse, gain, log_det, log_det_precision,
                        cholesky_work,
                    )  # fmt: skip
                for j in range(n_y):
                    innovation[j] = y[b, j] - outputs[j, i]
                if singular:
                    sample[:] = math.nan
                elif count == 1:
                    _draw(mean, H, gain[0], innovation, root_q, root_r[0], w[b, i], v[b, i], sample, process)  # fmt: skip
                    log_ratio = _proposal_log_density(
                        sample, mean, gain[0], innovation, H, q, components[0, 1],
                        log_det_precision[0], n_log_2pi, process,
                    )  # fmt: skip
                else:
                    for c in range(count):  # log weight times N(e; 0, S_c)
                        quadratic = 0.0
                        for j in range(n_y):
                            for m in range(n_y):
                                quadratic += innovation[j] * inverse[c, j, m] * innovation[m]
                        log_mixture[c] = log_component_weights[c] - 0.5 * (
                            quadratic + log_det[c] + n_y_log_2pi
                        )
                    normaliser = _logsumexp(log_mixture)
                    chosen, cumulative = 0, 0.0
                    for c in range(count):
                        log_mixture[c] = log_mixture[c] - normaliser
                        cumulative += math.exp(log_mixture[c])
                        if uniform[b, i] > cumulative:
                            chosen += 1
                    chosen = min(chosen, count - 1)
                    for c in range(count):
                        _draw(mean, H, gain[c], innovation, root_q, root_r[c], w[b, i], v[b, i], draws[c], process)  # fmt: skip
                    sample[:] = draws[chosen]
                    for c in range(count):
                        densities[c] = log_mixture[c] + _proposal_log_density(
                            sample, mean, gain[c], innovation, H, q, components[c, 1],
                            log_det_precision[c], n_log_2pi, process,
                        )  # fmt: skip
                    log_ratio = _logsumexp(densities)
                transition_sum = 0.0
                for k in range(n):
                    transition_sum += (sample[k] - mean[k]) ** 2
                log_ratio = log_ratio - (-0.5 * (transition_sum / q + transition_norm))
            else:
                noise = transition[b, i] if proposing else w[b, i]
                for k in range(n):
                    sample[k] = mean[k] + root_q * noise[k]
            for k in range(n):
                moved[k, i] = sample[k]
            log_ratios[i] = log_ratio
        constrain(moved, p)
        for i in range(n_particles):
            for k in range(n):
                particles[b, i, k] = moved[k, i]
        if measured:
            sensed_output(output, sense, q_output, s, moved, outputs)
            for i in range(n_particles):
                for j in range(n_y):
                    innovation[j] = y[b, j] - outputs[j, i]
                likelihood = log_likelihood(innovation, law, constants, gaussian_norm)
                log_weights[b, i] = log_weights[b, i] + likelihood - log_ratios[i]
