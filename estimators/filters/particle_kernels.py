"""The particle filter compiled: one call runs one trajectory from its first sample on.

:func:`filter_trajectory` does, for every step after the first sample, what
:meth:`kkl_bench.estimators.filters.particle_filter.ParticleFilter._filter` does in numpy:
the RK4 transition mean of every particle, the draw from the (locally optimal, or the
noise law's mixture of) proposal, the constraint, the importance weight with the noise
law's exact log-density, the normalisation, the estimate and systematic resampling, in
the same operations and order. It draws its standard normal and uniform numbers from the
trajectory's own ``numpy.random.Generator`` inside the kernel (numba runs numpy's
algorithms on the generator's state: the same numbers), in the order the reference
engine draws them, so the published random streams are kept and the two engines'
estimates agree to rounding (``tests/test_filter_engines.py``). Every scratch array is
allocated once a call; the particles stay in the model functions' layout ``(n_x, n)``
from step to step; the sensor's Jacobian is evaluated once where it is the same at every
point (:attr:`~kkl_bench.protocol.compiled.CompiledModel.constant_output_jacobian`).
The model's functions come in as first-class function values, so the kernel is compiled
once for every system and sensor (:func:`kkl_bench.support.kernel_cache.bind_once`).
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


@numba.njit(inline="always", error_model="numpy")
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
def log_likelihoods(y, outputs, law, constants, gaussian_norm, out):
    """``out (N,)``: ``log p(y - outputs[:, i])`` of the noise law ``law``
    (:func:`noise_law_constants`) for each of the ``N`` points of ``outputs (n_y, N)``,
    summed over the outputs, in the operations of
    :meth:`kkl_bench.measurement.NoiseLaw.log_density` (``gaussian_norm = n_y log(2 pi
    variance)`` for the Gaussian law)."""
    n_y, points = outputs.shape
    for i in range(points):
        total = 0.0
        if law == GAUSSIAN:
            for j in range(n_y):
                total += (y[j] - outputs[j, i]) ** 2
            out[i] = -0.5 * (total / constants[0] + gaussian_norm)
            continue
        for j in range(n_y):
            z = (y[j] - outputs[j, i]) / constants[0]
            if law == STUDENT_T:
                nu = constants[1]
                total += constants[2] - (nu + 1) / 2 * math.log1p(z**2 / nu)
            else:
                scale = constants[1]
                inlier = constants[2] - 0.5 * z**2
                outlier = constants[3] - 0.5 * (z / scale) ** 2
                total += _logaddexp(inlier, outlier) - constants[4] - constants[5]
        out[i] = total


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


@numba.njit(inline="always")
def _gain_times(c, gain, vectors, j, i, column):
    """Row ``j`` of component ``c``'s gain (``column``) times the point ``i`` of ``vectors
    (n_y, N)``."""
    total = 0.0
    for a in range(vectors.shape[0]):
        total += gain[c, j, a, column] * vectors[a, i]
    return total


@numba.njit(inline="always")
def _component_sample(c, process, innovations, v, means, H, gain, root_r, out, residual):
    """``out (n_x, N)``: each point's draw from component ``c``'s optimal proposal by
    Matheron's rule, ``mean + sqrt(q) w + gain (e - H sqrt(q) w - sqrt(r) v)``, from
    ``process = sqrt(q) w (n_x, N)``, the innovations ``e (n_y, N)`` and ``v (n_y, N)``.
    ``H (n_y, n_x, columns)`` and ``gain (count, n_x, n_y, columns)`` hold one column
    (the same at every point) or one a point; ``residual (n_y, N)`` is scratch."""
    n_y, n, columns = H.shape
    points = means.shape[1]
    for a in range(n_y):
        for i in range(points):
            column = i if columns > 1 else 0
            along = 0.0
            for m in range(n):
                along += H[a, m, column] * process[m, i]
            residual[a, i] = innovations[a, i] - along - root_r * v[a, i]
    for j in range(n):
        for i in range(points):
            correction = _gain_times(c, gain, residual, j, i, i if columns > 1 else 0)
            out[j, i] = means[j, i] + process[j, i] + correction


@numba.njit(inline="always")
def _component_log_density(c, sample, means, innovations, H, gain, q, r, log_det_precision, norm, offset, out):  # fmt: skip
    """``out (N,)``: ``log q_c(sample)`` of component ``c``'s optimal proposal, whose mean
    is ``mean + gain e`` (``_GaussianProposal.log_density``; ``norm = n_x log(2 pi)``,
    ``log_det_precision (count, columns)``; ``offset (n_x, N)`` scratch)."""
    n_y, n, columns = H.shape
    points = means.shape[1]
    for j in range(n):
        for i in range(points):
            correction = _gain_times(c, gain, innovations, j, i, i if columns > 1 else 0)
            offset[j, i] = sample[j, i] - (means[j, i] + correction)
    for i in range(points):
        column = i if columns > 1 else 0
        offset_sum = 0.0
        for j in range(n):
            offset_sum += offset[j, i] ** 2
        projected_sum = 0.0
        for a in range(n_y):
            along = 0.0
            for j in range(n):
                along += H[a, j, column] * offset[j, i]
            projected_sum += along**2
        quadratic = offset_sum / q + projected_sum / r
        out[i] = 0.5 * (log_det_precision[c, column] - quadratic - norm)


@numba.njit(inline="always")
def _fill_normals(rng, out):
    """``out (d, N)`` filled with standard normal numbers from ``rng`` point by point: the
    numbers an ``(N, d)`` draw in C order gives, one column a point."""
    for i in range(out.shape[1]):
        for j in range(out.shape[0]):
            out[j, i] = rng.standard_normal()


@numba.njit(inline="always")
def _store_covariances(H, q, components, column, Hs, gains, inverses, log_dets, log_det_precisions, singular, S, work):  # fmt: skip
    """Component by component, what the proposal takes from the Jacobian ``H (n_y, n_x)``
    alone (:func:`_proposal_covariances`) into column ``column`` of ``Hs``, ``gains``,
    ``inverses``, ``log_dets``, ``log_det_precisions`` and ``singular``."""
    singular[column] = not _proposal_covariances(
        H, q, components, S, inverses[:, :, :, column], gains[:, :, :, column],
        log_dets[:, column], log_det_precisions[:, column], work,
    )  # fmt: skip
    Hs[:, :, column] = H


@numba.njit(inline="always")
def _normalise_and_estimate(log_weights, weights, particles, out):
    """Log weights normalised in place, ``weights = exp(log_weights)`` and ``out (n_x,)``
    the weighted mean of ``particles (n_x, n)``."""
    total = _logsumexp(log_weights)
    for i in range(log_weights.shape[0]):
        log_weights[i] = log_weights[i] - total
        weights[i] = math.exp(log_weights[i])
    for k in range(particles.shape[0]):
        estimate = 0.0
        for i in range(particles.shape[1]):
            estimate += weights[i] * particles[k, i]
        out[k] = estimate


@numba.njit(inline="always")
def _resample(weights, offset, cumulative, particles, out):
    """``out (n_x, n)``: ``particles`` drawn by systematic resampling with the normalised
    ``weights (n,)`` and the uniform ``offset`` (NaN weights count as zero; the search
    of :func:`~kkl_bench.estimators.filters.particle_proposals.systematic_resample`)."""
    n = weights.shape[0]
    total = 0.0
    for i in range(n):
        weight = weights[i]
        total += 0.0 if math.isnan(weight) else weight
        cumulative[i] = total
    cumulative[n - 1] = 1.0
    ancestor = 0
    for i in range(n):
        position = (offset + i) / n
        while ancestor < n and cumulative[ancestor] <= position:
            ancestor += 1
        chosen = min(ancestor, n - 1)
        for k in range(particles.shape[0]):
            out[k, i] = particles[k, chosen]


@numba.njit(error_model="numpy")  # disk-cached, one for every model: kernel_cache.bind_once
def filter_trajectory(
    drift, output, output_jacobian, sense, sense_slope, constrain, p, q_output, s, g, rng,
    particles, log_weights, u, dt, y, present, proposing, all_present, q, components,
    constant_jacobian, law, constants, resample_below, out,
):  # fmt: skip
    """One trajectory through the particle filter (the module docstring).

    ``particles: (n_x, n)`` and ``log_weights: (n,)`` the first sample's (overwritten);
    ``u: (steps,)`` the inputs, ``y: (steps, n_y)`` the measurements, read where
    ``present: (steps,)``; ``proposing: (steps,)`` whether a step draws from the optimal
    proposal (the optimal proposal, and some trajectory of the batch measured then: the
    reference engine's draws depend on it) and ``all_present: (steps,)`` whether every
    trajectory of the batch is measured (else the step also draws a transition for the
    unmeasured ones); ``components: (c, 2)`` the proposal's Gaussian components
    ``(weight, variance)`` (one row unless the noise law is a mixture); ``law`` and
    ``constants`` the noise law (:func:`noise_law_constants`); ``out: (steps, n_x)`` the
    estimates, NaN-filled by the caller and left NaN from a step whose weights vanished.

    Each step draws, as the reference engine does: the process draws ``w: (n, n_x)``,
    then where proposing the measurement draws ``v: (n, n_y)``, the mixture's uniform
    numbers ``(n,)`` (more than one component) and the transition draws ``(n, n_x)``
    (not every trajectory measured); after each estimate but the last, one uniform
    number, the resampling offset. Every operation sweeps over the particles, one
    array a quantity with the particles on its last axis (as the model's functions do):
    a particle at a time, the small vectors and matrices of its proposal cost more than
    its arithmetic.
    """
    n, n_particles = particles.shape
    steps, n_y = y.shape
    count = components.shape[0]
    columns = 1 if constant_jacobian else n_particles  # of the proposal's matrices
    means, moved, spare = (
        np.empty((n, n_particles)),
        np.empty((n, n_particles)),
        np.empty((n, n_particles)),
    )
    work = np.empty((5, n, n_particles))
    u_points, log_ratios = np.empty(n_particles), np.empty(n_particles)
    weights, cumulative = np.empty(n_particles), np.empty(n_particles)
    outputs, slopes = np.empty((n_y, n_particles)), np.empty((n_y, n_particles))
    innovations, residual = np.empty((n_y, n_particles)), np.empty((n_y, n_particles))
    jacobians = np.empty((n_y, n, columns))
    first_point, first_output, first_slope = np.empty((n, 1)), np.empty((n_y, 1)), np.empty((n_y, 1))  # fmt: skip
    w, v, transition = np.empty((n, n_particles)), np.empty((n_y, n_particles)), np.empty((n, n_particles))  # fmt: skip
    uniform, process, offset = np.empty(n_particles), np.empty((n, n_particles)), np.empty((n, n_particles))  # fmt: skip
    Hs, H, H_used = np.empty((n_y, n, columns)), np.empty((n_y, n)), np.full((n_y, n), np.nan)
    gains, inverses = np.empty((count, n, n_y, columns)), np.empty((count, n_y, n_y, columns))
    log_dets, log_det_precisions = np.empty((count, columns)), np.empty((count, columns))
    singular = np.zeros(columns, dtype=np.bool_)
    S, cholesky_work = np.empty((count, n_y, n_y)), np.empty((n_y, n_y))
    samples = np.empty((count if count > 1 else 0, n, n_particles))
    log_mixture, densities = np.empty((count, n_particles)), np.empty((count, n_particles))
    mixture_terms, density = np.empty(count), np.empty(n_particles)
    root_q = math.sqrt(q)
    root_r = np.sqrt(components[:, 1])
    log_component_weights = np.log(components[:, 0])
    n_log_2pi, n_y_log_2pi = n * math.log(2 * math.pi), n_y * math.log(2 * math.pi)
    transition_norm = n * math.log(2 * math.pi * q)
    gaussian_norm = n_y * math.log(2 * math.pi * constants[0]) if law == GAUSSIAN else 0.0
    uniform_log_weight = -math.log(n_particles)
    for k in range(steps):
        if k > 0:
            _fill_normals(rng, w)
            if proposing[k]:
                _fill_normals(rng, v)
                if count > 1:
                    for i in range(n_particles):
                        uniform[i] = rng.random()
                if not all_present[k]:
                    _fill_normals(rng, transition)
            u_points[:] = u[k - 1]
            rk4_step(drift, p, g, particles, u_points, dt, means, work)
            if proposing[k] and present[k]:
                if not constant_jacobian:
                    _sensed_output_jacobian(output, output_jacobian, sense_slope, q_output, s, means, outputs, slopes, jacobians)  # fmt: skip
                elif math.isnan(H_used[0, 0]):  # the one Jacobian, at the first particle
                    for j in range(n):  # a copy: the model's functions take C-contiguous arrays
                        first_point[j, 0] = means[j, 0]
                    _sensed_output_jacobian(output, output_jacobian, sense_slope, q_output, s, first_point, first_output, first_slope, jacobians)  # fmt: skip
                for i in range(columns):  # a new Jacobian: its proposal's matrices
                    changed = False
                    for a in range(n_y):
                        for j in range(n):
                            H[a, j] = jacobians[a, j, i]
                            changed = changed or H[a, j] != H_used[a, j]
                    if changed:
                        H_used[:, :] = H
                        _store_covariances(H, q, components, i, Hs, gains, inverses, log_dets, log_det_precisions, singular, S, cholesky_work)  # fmt: skip
                    elif not constant_jacobian:
                        Hs[:, :, i] = Hs[:, :, i - 1]
                        gains[:, :, :, i] = gains[:, :, :, i - 1]
                        inverses[:, :, :, i] = inverses[:, :, :, i - 1]
                        log_dets[:, i] = log_dets[:, i - 1]
                        log_det_precisions[:, i] = log_det_precisions[:, i - 1]
                        singular[i] = singular[i - 1]
                sensed_output(output, sense, q_output, s, means, outputs)
                for a in range(n_y):
                    for i in range(n_particles):
                        innovations[a, i] = y[k, a] - outputs[a, i]
                for j in range(n):
                    for i in range(n_particles):
                        process[j, i] = root_q * w[j, i]
                if count == 1:
                    _component_sample(0, process, innovations, v, means, Hs, gains, root_r[0], moved, residual)  # fmt: skip
                    _component_log_density(0, moved, means, innovations, Hs, gains, q, components[0, 1], log_det_precisions, n_log_2pi, offset, log_ratios)  # fmt: skip
                else:
                    for c in range(count):  # each component's weight times N(e; 0, S_c)
                        _component_sample(c, process, innovations, v, means, Hs, gains, root_r[c], samples[c], residual)  # fmt: skip
                        for i in range(n_particles):
                            column = i if columns > 1 else 0
                            quadratic = 0.0
                            for a in range(n_y):
                                for b in range(n_y):
                                    quadratic += innovations[a, i] * inverses[c, a, b, column] * innovations[b, i]  # fmt: skip
                            log_mixture[c, i] = log_component_weights[c] - 0.5 * (
                                quadratic + log_dets[c, column] + n_y_log_2pi
                            )
                    for i in range(n_particles):  # normalised; the uniform picks one
                        for c in range(count):
                            mixture_terms[c] = log_mixture[c, i]
                        normaliser = _logsumexp(mixture_terms)
                        chosen, total = 0, 0.0
                        for c in range(count):
                            log_mixture[c, i] = log_mixture[c, i] - normaliser
                            total += math.exp(log_mixture[c, i])
                            if uniform[i] > total:
                                chosen += 1
                        chosen = min(chosen, count - 1)
                        for j in range(n):
                            moved[j, i] = samples[chosen, j, i]
                    for c in range(count):
                        _component_log_density(c, moved, means, innovations, Hs, gains, q, components[c, 1], log_det_precisions, n_log_2pi, offset, density)  # fmt: skip
                        for i in range(n_particles):
                            densities[c, i] = log_mixture[c, i] + density[i]
                    for i in range(n_particles):
                        for c in range(count):
                            mixture_terms[c] = densities[c, i]
                        log_ratios[i] = _logsumexp(mixture_terms)
                for i in range(n_particles):
                    if singular[i if columns > 1 else 0]:
                        for j in range(n):
                            moved[j, i] = math.nan
                    transition_sum = 0.0
                    for j in range(n):
                        transition_sum += (moved[j, i] - means[j, i]) ** 2
                    log_ratios[i] = log_ratios[i] - (-0.5 * (transition_sum / q + transition_norm))
            else:
                noise = transition if proposing[k] else w
                for j in range(n):
                    for i in range(n_particles):
                        moved[j, i] = means[j, i] + root_q * noise[j, i]
                log_ratios[:] = 0.0
            constrain(moved, p)
            particles, moved = moved, particles
            if present[k]:
                sensed_output(output, sense, q_output, s, particles, outputs)
                log_likelihoods(y[k], outputs, law, constants, gaussian_norm, density)
                for i in range(n_particles):
                    log_weights[i] = log_weights[i] + density[i] - log_ratios[i]
        _normalise_and_estimate(log_weights, weights, particles, out[k])
        stopped = False
        for j in range(n):
            stopped = stopped or math.isnan(out[k, j])
        if stopped:  # every weight vanished: NaN from here on
            out[k:, :] = math.nan
            return
        if k + 1 < steps:
            squares = 0.0
            for i in range(n_particles):
                squares += weights[i] ** 2
            offset_draw = rng.random()
            if 1.0 / squares < resample_below * n_particles:
                _resample(weights, offset_draw, cumulative, particles, spare)
                particles, spare = spare, particles
                log_weights[:] = uniform_log_weight
