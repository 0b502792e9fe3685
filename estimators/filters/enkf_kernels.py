"""The ensemble transform Kalman filter compiled: the arithmetic of ``estimators/filters/enkf.py``
without Python in the loop.

:func:`etkf` runs one trajectory through the ETKF (global, or local per site: the
LETKF) with the operations of :func:`kkl_bench.estimators.filters.enkf.transform` and
:func:`~kkl_bench.estimators.filters.enkf.local_transform` in the same order, on random numbers
the caller draws from the trajectory's own generator exactly as the reference engine
draws them (the first ensemble, then each step's process noise), so its estimates equal
the reference engine's to rounding (``tests/test_filter_engines.py``). With fewer
outputs than members the analysis takes the eigendecomposition of an ``m x m`` matrix
where the reference takes one of ``N x N`` (:func:`_analyse`): the same matrices, so
the two engines differ in the last bits of each analysis.

Shapes: ``y: (steps, n_y)`` (NaN where no measurement), ``u: (steps,)``, ``initial:
(N, n_x)``, ``noise: (steps - 1, N, n_x)`` (empty without process noise), ``near:
(sites, m)`` and ``taper: (sites, m)`` (``sites = 0``: the global analysis), ``out:
(steps, n_x)`` filled with NaN by the caller.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from kkl_bench.estimators.filters.kalman_kernels import all_finite

from kkl_bench.protocol.compiled import rk4_step, sensed_output


@numba.njit(cache=True)
def _mean_over_members(values, out):
    """``out (k,)`` = the mean of ``values (N, k)`` over its rows, summed in row order."""
    out[:] = values[0]
    for i in range(1, values.shape[0]):
        for j in range(values.shape[1]):
            out[j] += values[i, j]
    for j in range(values.shape[1]):
        out[j] /= values.shape[0]


@numba.njit(cache=True)
def _analyse(anomalies_y, precision_weights, innovation, anomalies, mean, out):
    """``out (N, k)``: the ETKF analysis members ``x_bar + (w_bar + W_a[i]) A``
    (``estimators/filters/enkf.py``) of states with forecast ``mean (k,)`` and ``anomalies (N, k)``,
    from the output anomalies ``anomalies_y (N, m)`` (``Y_b^T``), the precision of each
    output ``precision_weights (m,)`` (``R^-1``'s diagonal) and the ``innovation (m,)``.

    With fewer outputs than members the ``N x N`` matrix ``(N - 1) I + B B^T`` (``B =
    Y_b^T R^-1/2``) is a rank-``m`` update of a multiple of the identity, so its inverse and
    the symmetric square root come from the eigendecomposition of the ``m x m`` matrix
    ``B^T B = U diag(l) U^T``: with ``E = B U`` and ``a = N - 1``,
    ``P_a = (I - E diag(1 / (a + l)) E^T) / a`` and ``W_a = [(N - 1) P_a]^(1/2) = I + E
    diag(g) E^T``, ``g = -1 / (sqrt(a + l) (sqrt(a) + sqrt(a + l)))`` (``sqrt(a / (a + l)) -
    1`` over ``l``, in a form without the division), and ``W_a A = A + E diag(g) (E^T A)``.
    The same matrices as the ``N x N`` eigendecomposition the reference engine takes, in
    ``O(N m (m + k))`` instead of ``O(N^2 (N + k))``; with as many outputs as members or
    more, that eigendecomposition."""
    members, outputs = anomalies_y.shape
    states = anomalies.shape[1]
    a = members - 1.0
    scaled = anomalies_y * precision_weights  # C^T
    projected = scaled @ innovation  # C (y - y_bar): (N,)
    if outputs >= members:
        precision = scaled @ np.ascontiguousarray(anomalies_y.T)
        for i in range(members):
            precision[i, i] += a
        values, vectors = np.linalg.eigh(precision)  # symmetric positive definite
        rotated = projected @ vectors
        for j in range(members):
            rotated[j] /= values[j]
        vectors_t = np.ascontiguousarray(vectors.T)
        weights = rotated @ vectors_t
        scaled_vectors = vectors.copy()
        for j in range(members):
            factor = math.sqrt(a / values[j])
            for i in range(members):
                scaled_vectors[i, j] *= factor
        transform = scaled_vectors @ vectors_t
        for i in range(members):
            for j in range(members):
                transform[i, j] += weights[j]
        out[:, :] = transform @ anomalies
        for i in range(members):
            for j in range(states):
                out[i, j] += mean[j]
        return
    b = anomalies_y * np.sqrt(precision_weights)
    b_t = np.ascontiguousarray(b.T)
    gram = b_t @ b
    if outputs == 1:
        values, rotation = np.array([gram[0, 0]]), np.ones((1, 1))
    else:
        values, rotation = np.linalg.eigh(gram)
    e = b @ rotation  # (N, m)
    along = np.ascontiguousarray(e.T) @ projected
    weights = projected.copy()
    for k in range(outputs):
        coefficient = along[k] / (a + values[k])
        for j in range(members):
            weights[j] -= e[j, k] * coefficient
    for j in range(members):
        weights[j] /= a
    shrink = np.empty(outputs)
    for k in range(outputs):
        total = math.sqrt(a + values[k])
        shrink[k] = -1.0 / (total * (math.sqrt(a) + total))
    shift = mean.copy()  # x_bar + w_bar A
    projected_anomalies = np.zeros((outputs, states))  # diag(g) E^T A
    for j in range(members):
        for s in range(states):
            shift[s] += weights[j] * anomalies[j, s]
        for k in range(outputs):
            for s in range(states):
                projected_anomalies[k, s] += e[j, k] * anomalies[j, s]
    for k in range(outputs):
        for s in range(states):
            projected_anomalies[k, s] *= shrink[k]
    for i in range(members):
        for s in range(states):
            total = shift[s] + anomalies[i, s]
            for k in range(outputs):
                total += e[i, k] * projected_anomalies[k, s]
            out[i, s] = total


@numba.njit  # disk-cached once bound to a model: kernel_cache.bind
def etkf(
    drift, output, sense, constrain, p, q, s, g, y, u, dt, sigma_w, r, inflation, near, taper,
    initial, noise, out,
):  # fmt: skip
    """One trajectory through the ensemble transform Kalman filter with multiplicative
    inflation of the analysis anomalies (the module docstring; ``r`` the measurement
    noise variance). The ensemble stops (NaN from there on) where it stops being
    finite."""
    steps, n_y = y.shape
    members, n = initial.shape
    sites = near.shape[0]
    ensemble = initial.copy()
    members_swept, following = np.empty((n, members)), np.empty((n, members))
    outputs, work, u_members = (
        np.empty((n_y, members)),
        np.empty((5, n, members)),
        np.empty(members),
    )
    predicted = np.empty((members, n_y))
    mean, predicted_mean = np.empty(n), np.empty(n_y)
    anomalies = np.empty((members, n))
    weights = np.full(n_y, 1.0 / r)  # R^-1 of the global analysis
    per_site = n // sites if sites else n
    local = np.empty((members, per_site))
    for k in range(steps):
        if k > 0:
            for i in range(members):
                for j in range(n):
                    members_swept[j, i] = ensemble[i, j]
            u_members[:] = u[k - 1]
            rk4_step(drift, p, g, members_swept, u_members, dt, following, work)
            if sigma_w != 0.0:
                for i in range(members):
                    for j in range(n):
                        following[j, i] = following[j, i] + sigma_w * noise[k - 1, i, j]
            constrain(following, p)
            for i in range(members):
                for j in range(n):
                    ensemble[i, j] = following[j, i]
        if all_finite(y[k]) and all_finite(ensemble.ravel()):
            for i in range(members):
                for j in range(n):
                    members_swept[j, i] = ensemble[i, j]
            sensed_output(output, sense, q, s, members_swept, outputs)
            for i in range(members):
                for j in range(n_y):
                    predicted[i, j] = outputs[j, i]
            _mean_over_members(ensemble, mean)
            _mean_over_members(predicted, predicted_mean)
            for i in range(members):
                for j in range(n):
                    anomalies[i, j] = ensemble[i, j] - mean[j]
                for j in range(n_y):
                    predicted[i, j] = predicted[i, j] - predicted_mean[j]
            innovation = y[k] - predicted_mean
            if sites == 0:
                _analyse(predicted, weights, innovation, anomalies, mean, ensemble)
            else:
                for site in range(sites):
                    states = slice(site * per_site, (site + 1) * per_site)
                    local_y = np.ascontiguousarray(predicted[:, near[site]])
                    _analyse(
                        local_y, taper[site] / r, innovation[near[site]],
                        np.ascontiguousarray(anomalies[:, states]), mean[states], local,
                    )  # fmt: skip
                    ensemble[:, states] = local
            _mean_over_members(ensemble, mean)
            for i in range(members):
                for j in range(n):
                    ensemble[i, j] = mean[j] + inflation * (ensemble[i, j] - mean[j])
        _mean_over_members(ensemble, out[k])
        if not all_finite(out[k]):
            break
