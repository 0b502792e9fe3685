"""The ensemble transform Kalman filter compiled: the arithmetic of ``estimators/filters/enkf.py``
without Python in the loop.

:func:`etkf` runs one trajectory through the ETKF (global, or local per site: the
LETKF) with the operations of :func:`kkl_bench.estimators.filters.enkf.transform` and
:func:`~kkl_bench.estimators.filters.enkf.local_transform` in the same order. It draws its
random numbers from the trajectory's own ``numpy.random.Generator`` inside the kernel
(numba runs numpy's algorithms on the generator's state: the same numbers), in the order
the reference engine draws them (the first ensemble, then each step's process noise),
so its estimates equal the reference engine's to rounding
(``tests/test_filter_engines.py``). With fewer outputs than members the analysis takes
the eigendecomposition of an ``m x m`` matrix where the reference takes one of ``N x N``
(:func:`_analyse`): the same matrices, so the two engines differ in the last bits of
each analysis. The ensemble stays in the model functions' layout ``(n_x, N)``, the
members on the last axis, every loop over the members innermost; the RK4 transition is
the system's traced one where it traces (:mod:`kkl_bench.estimators.filters.traced_transition`,
bit for bit the sweep's), and the analysis with fewer outputs than members, every paper
and hard cell's, allocates nothing: its scratch (:func:`scratch_for`) is allocated once
a trajectory.

Shapes: ``y: (steps, n_y)`` (NaN where no measurement), ``u: (steps,)``, ``low, high:
(n_x,)`` the box the first ensemble is drawn from, ``near: (sites, m)`` and ``taper:
(sites, m)`` (``sites = 0``: the global analysis), ``out: (steps, n_x)`` filled with NaN
by the caller.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from kkl_bench.protocol.compiled import rk4_step, sensed_output


@numba.njit(inline="always", error_model="numpy")
def _mean_over_members(values, row, out):
    """``out[row] =`` the mean of ``values[row, :]`` over the members, summed in order (the
    reference's ``mean(axis=1)`` of its ``(N, k)`` members, row by row)."""
    total = values[row, 0]
    for i in range(1, values.shape[1]):
        total += values[row, i]
    out[row] = total / values.shape[1]


@numba.njit(inline="always", error_model="numpy")
def _analyse(predicted, precision_weights, innovation, ensemble, mean, first, states, weights, scratch):  # fmt: skip
    """The states ``first..first + k`` of the members ``ensemble (n_x, N)``, whose mean is
    ``mean (n_x,)``, replaced by the ETKF analysis members ``x_bar + (w_bar + W_a[i]) A``
    (``estimators/filters/enkf.py``; ``A`` the members' anomalies) and their ``mean`` by the
    analysis members' mean, from the output anomalies ``predicted (m, N)`` (``Y_b``), the
    precision of each output ``precision_weights (m,)`` (``R^-1``'s diagonal) and the
    ``innovation (m,)``.

    With fewer outputs than members the ``N x N`` matrix ``(N - 1) I + B B^T`` (``B =
    Y_b^T R^-1/2``) is a rank-``m`` update of a multiple of the identity, so its inverse and
    the symmetric square root come from the eigendecomposition of the ``m x m`` matrix
    ``B^T B = U diag(l) U^T``: with ``E = B U`` and ``a = N - 1``,
    ``P_a = (I - E diag(1 / (a + l)) E^T) / a`` and ``W_a = [(N - 1) P_a]^(1/2) = I + E
    diag(g) E^T``, ``g = -1 / (sqrt(a + l) (sqrt(a) + sqrt(a + l)))`` (``sqrt(a / (a + l)) -
    1`` over ``l``, in a form without the division), and ``W_a A = A + E diag(g) (E^T A)``.
    The same matrices as the ``N x N`` eigendecomposition the reference engine takes, in
    ``O(N m (m + k))`` instead of ``O(N^2 (N + k))``, in ``weights (N,)`` and the arrays
    of ``scratch`` (:func:`scratch_for`); with as many outputs as members or more, that
    eigendecomposition (:func:`_analyse_full`)."""
    outputs, members = predicted.shape
    if outputs == 1:
        _analyse_one_output(predicted, precision_weights[0], innovation[0], ensemble, mean, first, states, weights)  # fmt: skip
        return
    anomalies = scratch[0]
    for s in range(first, first + states):
        for i in range(members):
            anomalies[s, i] = ensemble[s, i] - mean[s]
    if outputs >= members:
        _analyse_full(predicted, precision_weights, innovation, anomalies, mean, first, states, ensemble)  # fmt: skip
    else:
        _analyse_low_rank(predicted, precision_weights, innovation, anomalies, mean, first, states, ensemble, weights, scratch)  # fmt: skip
    for s in range(first, first + states):
        _mean_over_members(ensemble, s, mean)


@numba.njit(inline="always", error_model="numpy")
def _analyse_low_rank(predicted, precision_weights, innovation, anomalies, mean, first, states, out, weights, scratch):  # fmt: skip
    """:func:`_analyse` with more than one output, fewer than the members, into ``out``
    from the ``anomalies (n_x, N)``."""
    outputs, members = predicted.shape
    a = members - 1.0
    _, projected, b, e, gram, along, shrink, shift, projected_anomalies = scratch
    for j in range(members):  # C (y - y_bar), C^T = Y_b^T R^-1; B = Y_b^T R^-1/2
        total = 0.0
        for k in range(outputs):
            total += predicted[k, j] * precision_weights[k] * innovation[k]
        projected[j] = total
    for k in range(outputs):
        root = math.sqrt(precision_weights[k])
        for j in range(members):
            b[k, j] = predicted[k, j] * root
    for k in range(outputs):
        for m in range(outputs):
            total = 0.0
            for j in range(members):
                total += b[k, j] * b[m, j]
            gram[k, m] = total
    values, rotation = np.linalg.eigh(gram)
    for k in range(outputs):
        for j in range(members):
            total = 0.0
            for m in range(outputs):
                total += b[m, j] * rotation[m, k]
            e[k, j] = total
    for k in range(outputs):
        total = 0.0
        for j in range(members):
            total += e[k, j] * projected[j]
        along[k] = total / (a + values[k])
        root = math.sqrt(a + values[k])
        shrink[k] = -1.0 / (root * (math.sqrt(a) + root))
    for j in range(members):  # w_bar = P_a C (y - y_bar)
        total = projected[j]
        for k in range(outputs):
            total -= e[k, j] * along[k]
        weights[j] = total / a
    for s in range(states):  # x_bar + w_bar A, and diag(g) E^T A
        total = mean[first + s]
        for j in range(members):
            total += weights[j] * anomalies[first + s, j]
        shift[s] = total
        for k in range(outputs):
            total = 0.0
            for j in range(members):
                total += e[k, j] * anomalies[first + s, j]
            projected_anomalies[k, s] = total * shrink[k]
    for s in range(states):
        for i in range(members):
            total = shift[s] + anomalies[first + s, i]
            for k in range(outputs):
                total += e[k, i] * projected_anomalies[k, s]
            out[first + s, i] = total


@numba.njit(inline="always", error_model="numpy")
def _analyse_one_output(predicted, weight, innovation, ensemble, mean, first, states, weights):  # fmt: skip
    """:func:`_analyse` for one output, in scalars: ``B^T B`` is the number ``l`` and ``E =
    B``, the same operations as the general path's with ``m = 1``, each member's ``B``,
    ``C (y - y_bar)`` and anomaly recomputed where used rather than stored (a loop over one
    output inside every loop over the members, and the stores, cost more than the
    analysis)."""
    members = predicted.shape[1]
    a = members - 1.0
    root = math.sqrt(weight)
    gram, along = 0.0, 0.0
    for j in range(members):
        b = predicted[0, j] * root
        gram += b * b
        along += b * (predicted[0, j] * weight * innovation)
    along = along / (a + gram)
    total = math.sqrt(a + gram)
    shrink = -1.0 / (total * (math.sqrt(a) + total))
    for j in range(members):
        weights[j] = (predicted[0, j] * weight * innovation - predicted[0, j] * root * along) / a
    for s in range(first, first + states):
        shift, projected_anomaly = mean[s], 0.0
        for j in range(members):
            anomaly = ensemble[s, j] - mean[s]
            shift += weights[j] * anomaly
            projected_anomaly += predicted[0, j] * root * anomaly
        projected_anomaly = projected_anomaly * shrink
        total = 0.0
        for i in range(members):
            value = shift + (ensemble[s, i] - mean[s]) + predicted[0, i] * root * projected_anomaly
            ensemble[s, i] = value
            total += value
        mean[s] = total / members


@numba.njit(cache=True, error_model="numpy")
def _analyse_full(predicted, precision_weights, innovation, anomalies, mean, first, states, out):  # fmt: skip
    """:func:`_analyse` with as many outputs as members or more: the ``N x N``
    eigendecomposition of ``(N - 1) I + C Y_b^T``, as the reference engine takes it."""
    members = predicted.shape[1]
    a = members - 1.0
    predicted_t = np.ascontiguousarray(predicted.T)  # Y_b^T: (N, m)
    scaled = predicted_t * precision_weights  # C^T
    projected = scaled @ innovation  # C (y - y_bar): (N,)
    precision = scaled @ predicted
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
    local = np.ascontiguousarray(anomalies[first : first + states].T)  # (N, k)
    updated = transform @ local
    for s in range(states):
        for i in range(members):
            out[first + s, i] = updated[i, s] + mean[first + s]


@numba.njit(cache=True)
def scratch_for(members, outputs, states, states_total):
    """The arrays :func:`_analyse` works in for ``members`` members and up to ``outputs``
    outputs (more than one), ``states`` states analysed together of ``states_total``,
    ``weights`` aside."""
    return (
        np.empty((states_total, members)),
        np.empty(members),
        np.empty((outputs, members)),
        np.empty((outputs, members)),
        np.empty((outputs, outputs)),
        np.empty(outputs),
        np.empty(outputs),
        np.empty(states),
        np.empty((outputs, states)),
    )


@numba.njit(cache=True)
def untraced(x, p, s, g, u, dt, out):
    """The traced transition's place for a model without one (never called)."""


@numba.njit(error_model="numpy")  # disk-cached once bound to a model: kernel_cache.bind
def etkf(
    drift, output, sense, constrain, transition, p, q, s, g, traced, rng, y, u, dt, sigma_w,
    r, inflation, near, taper, low, high, members, out,
):  # fmt: skip
    """One trajectory through the ensemble transform Kalman filter of ``members``
    members with multiplicative inflation of the analysis anomalies (the module
    docstring; ``r`` the measurement noise variance), drawing from ``rng``; the RK4
    transition by ``transition`` where ``traced``, else by the sweep over ``drift``. The
    ensemble stops (NaN from there on) where it stops being finite."""
    steps, n_y = y.shape
    n = low.shape[0]
    sites = near.shape[0]
    ensemble, following = np.empty((n, members)), np.empty((n, members))
    for i in range(members):  # the reference's rng.uniform(low, high, (members, n))
        for j in range(n):
            ensemble[j, i] = low[j] + (high[j] - low[j]) * rng.random()
    outputs, work, u_members = np.empty((n_y, members)), np.empty((5, n, members)), np.empty(members)  # fmt: skip
    mean, predicted_mean, innovation = np.empty(n), np.empty(n_y), np.empty(n_y)
    precisions = np.full(n_y, 1.0 / r)  # R^-1 of the global analysis
    member_weights = np.empty(members)
    per_site = n // sites if sites else n
    local_outputs = near.shape[1] if sites else n_y
    local_y, local_weights = np.empty((local_outputs, members)), np.empty(local_outputs)
    local_innovation = np.empty(local_outputs)
    scratch = scratch_for(members, local_outputs, per_site, n)
    for k in range(steps):
        if k > 0:
            u_members[:] = u[k - 1]
            if traced:
                transition(ensemble, p, s, g, u_members, dt, following)
            else:
                rk4_step(drift, p, g, ensemble, u_members, dt, following, work)
            if sigma_w != 0.0:
                for i in range(members):  # the reference's (members, n) draw, in C order
                    for j in range(n):
                        following[j, i] = following[j, i] + sigma_w * rng.standard_normal()
            constrain(following, p)
            ensemble, following = following, ensemble
        check = 0.0  # x - x: NaN for a member that is not finite
        for j in range(n):
            total = 0.0
            for i in range(members):
                value = ensemble[j, i]
                total += value
                check += value - value
            mean[j] = total / members
        for j in range(n_y):
            check += y[k, j] - y[k, j]
        if check == 0.0:  # every member finite, and the sample measured
            sensed_output(output, sense, q, s, ensemble, outputs)
            for j in range(n_y):
                _mean_over_members(outputs, j, predicted_mean)
                for i in range(members):
                    outputs[j, i] = outputs[j, i] - predicted_mean[j]
                innovation[j] = y[k, j] - predicted_mean[j]
            if sites == 0:
                _analyse(outputs, precisions, innovation, ensemble, mean, 0, n, member_weights, scratch)  # fmt: skip
            else:
                for site in range(sites):
                    for c in range(local_outputs):
                        output_index = near[site, c]
                        local_weights[c] = taper[site, c] / r
                        local_innovation[c] = innovation[output_index]
                        for i in range(members):
                            local_y[c, i] = outputs[output_index, i]
                    _analyse(
                        local_y, local_weights, local_innovation, ensemble, mean,
                        site * per_site, per_site, member_weights, scratch,
                    )  # fmt: skip
            for j in range(n):  # the inflation, and the estimate: the members' mean
                total = 0.0
                for i in range(members):
                    value = mean[j] + inflation * (ensemble[j, i] - mean[j])
                    ensemble[j, i] = value
                    total += value
                mean[j] = total / members
        finite = True
        for j in range(n):
            out[k, j] = mean[j]
            finite = finite and math.isfinite(mean[j])
        if not finite:
            break
