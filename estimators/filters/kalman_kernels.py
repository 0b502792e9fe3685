"""The EKF and the UKF compiled: the same arithmetic as filterpy's, without Python in the loop.

Each kernel advances a batch of trajectories together through one filter with the
protocol's settings (``docs/protocol.md`` section 6) and the operations of filterpy's
``ExtendedKalmanFilter`` and ``UnscentedKalmanFilter`` (Merwe scaled sigma points,
Cholesky square root) in the same order, so its estimates equal the reference
engine's to rounding (``tests/test_filter_engines.py`` checks a relative 1e-9 on every
quick-profile cell of the paper and hard tracks). The model comes as a
:class:`~kkl_bench.protocol.compiled.CompiledModel`'s functions, which sweep over the
batch: every state, matrix and scratch array keeps the trajectories on its last axis
(``x: (n_x, batch)``, ``P: (n_x, n_x, batch)``), so each operation is one loop over
contiguous memory for all trajectories (protocol 6.3 gives what this layout saves).

A trajectory whose innovation covariance is singular, or whose covariance is not
positive definite where the UKF needs its square root, stops there and keeps NaN for
the rest of its samples, as the reference engine does; so does one whose estimate
stops being finite (that estimate is kept). A stopped trajectory's lane goes on being
computed with the others and is never written; a trajectory without a measurement at a
sample keeps its prediction there.

Shapes: ``y: (batch, steps, n_y)`` (NaN where no measurement), ``u: (batch, steps)``,
``x0: (n_x,)``, ``P0, Q: (n_x, n_x)``, ``R: (n_y, n_y)``, ``out: (batch, steps, n_x)``
filled with NaN by the caller.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from kkl_bench.estimators.filters.kalman_linalg import (
    add,
    add_each,
    broadcast,
    inflate,
    invert_each,
    matmul,
    matmul_transposed,
    positive_definite,
    upper_cholesky,
)

from kkl_bench.protocol.compiled import rk4_step, rk4_step_jacobian, sensed_output


@numba.njit(cache=True)
def all_finite(values):
    """Whether every entry of the one-dimensional ``values`` is finite."""
    for value in values:  # noqa: SIM110 (a loop numba compiles)
        if not math.isfinite(value):
            return False
    return True


@numba.njit(inline="always")
def _record(x, alive, k, out):
    """``out[b, k] = x[:, b]`` for every trajectory still running; one whose estimate is no
    longer finite stops after this sample."""
    n, batch = x.shape
    for b in range(batch):
        if alive[b]:
            for i in range(n):
                out[b, k, i] = x[i, b]
            finite = True
            for i in range(n):
                finite = finite and math.isfinite(x[i, b])
            alive[b] = finite


@numba.njit(inline="always")
def _measured_now(y, k, alive, measured):
    """``measured[b]``: trajectory ``b`` runs and has its measurement at sample ``k``;
    returns whether any does."""
    any_measured = False
    for b in range(y.shape[0]):
        measured[b] = alive[b] and all_finite(y[b, k])
        any_measured = any_measured or measured[b]
    return any_measured


@numba.njit(inline="always")
def _stop_singular(alive, measured, invertible):
    """A measured trajectory whose innovation covariance is singular stops before this
    sample (``alive[b] = False``) and takes no update (``measured[b] = False``)."""
    for b in range(alive.shape[0]):
        alive[b] = alive[b] and (invertible[b] or not measured[b])
        measured[b] = measured[b] and invertible[b]


@numba.njit(inline="always")
def _sensed_output_jacobian(output, output_jacobian, sense_slope, q, s, x, h, slope, out):
    """``out (n_y, n_x, m)`` = the Jacobian of ``s(h(x))`` at the points ``x (n_x, m)``:
    the sensor's slope at ``h(x)`` times ``dh/dx``
    (:meth:`kkl_bench.measurement.SensedSystem.h_jacobian`)."""
    output(x, q, h)
    sense_slope(h, s, slope)
    output_jacobian(x, q, out)
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            for point in range(out.shape[2]):
                out[j, i, point] = slope[j, point] * out[j, i, point]


@numba.njit(inline="always")
def _huber_noise(R, residual, S, threshold, out):
    """``out[:, :, b]`` = ``R`` (diagonal) with each output's variance divided by its Huber
    weight ``min(1, threshold / e)``, ``e = |residual_j| / sqrt(S_jj)``, for every trajectory
    (:func:`kkl_bench.estimators.filters.kalman.huber_noise`, in the same operations)."""
    out[:, :, :] = 0.0
    for j in range(R.shape[0]):
        for b in range(out.shape[2]):
            normalized = abs(residual[j, b]) / math.sqrt(S[j, j, b])
            weight = threshold / normalized if normalized > 0.0 else math.inf
            out[j, j, b] = R[j, j] / min(1.0, weight)


@numba.njit  # disk-cached once bound to a model: kernel_cache.bind
def ekf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, inflation, threshold, out,
):  # fmt: skip
    """filterpy's ``ExtendedKalmanFilter`` with the RK4 transition (``estimators/filters/ekf.py``):
    predict ``x = C(RK4(x))`` (``C`` the constraint), ``P = F P F^T + Q`` (``inflation
    (F P F^T) + Q`` with inflation), ``F`` the RK4 step's Jacobian at the posterior mean;
    update in Joseph form ``P = (I - K H) P (I - K H)^T + K R K^T``, with ``R`` Huber's
    (:func:`_huber_noise`) for a finite ``threshold``."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    x, x_next, u_previous = np.empty((n, batch)), np.empty((n, batch)), np.empty(batch)
    P, F, FP = np.empty((n, n, batch)), np.empty((n, n, batch)), np.empty((n, n, batch))
    work, jacobian_work = np.empty((5, n, batch)), np.empty((5, n, n, batch))
    H, PHT = np.empty((n_y, n, batch)), np.empty((n, n_y, batch))
    S, SI = np.empty((n_y, n_y, batch)), np.empty((n_y, n_y, batch))
    K, KR = np.empty((n, n_y, batch)), np.empty((n, n_y, batch))
    I_KH, I_KHP = np.empty((n, n, batch)), np.empty((n, n, batch))
    h, slope = np.empty((n_y, batch)), np.empty((n_y, batch))
    R_used = np.empty((n_y, n_y, batch))
    alive, measured, invertible = (
        np.ones(batch, np.bool_),
        np.empty(batch, np.bool_),
        np.empty(batch, np.bool_),
    )
    robust = math.isfinite(threshold)
    for i in range(n):
        x[i, :] = x0[i]
    broadcast(P0, P)
    broadcast(R, R_used)
    for k in range(steps):
        if k > 0:
            for b in range(batch):
                u_previous[b] = u[b, k - 1]
            rk4_step_jacobian(
                drift, drift_jacobian, p, g, x, u_previous, dt, F, work, jacobian_work
            )
            rk4_step(drift, p, g, x, u_previous, dt, x_next, work)
            constrain(x_next, p)
            x[:, :] = x_next
            matmul(F, P, FP)
            matmul_transposed(FP, F, P)
            add_each(P, Q)
            if inflation != 1.0:
                inflate(P, Q, inflation)
        if _measured_now(y, k, alive, measured):
            _sensed_output_jacobian(output, output_jacobian, sense_slope, q, s, x, h, slope, H)
            matmul_transposed(P, H, PHT)
            matmul(H, PHT, S)
            sensed_output(output, sense, q, s, x, h)
            for j in range(n_y):
                for b in range(batch):
                    h[j, b] = y[b, k, j] - h[j, b]
            if robust:
                SI[:, :, :] = S
                add_each(SI, R)
                _huber_noise(R, h, SI, threshold, R_used)
            add(S, R_used)
            invert_each(S, SI, invertible)
            matmul(PHT, SI, K)
            _stop_singular(alive, measured, invertible)
            for i in range(n):
                for b in range(batch):
                    correction = 0.0
                    for j in range(n_y):
                        correction += K[i, j, b] * h[j, b]
                    if measured[b]:
                        x[i, b] = x[i, b] + correction
            for i in range(n):
                for j in range(n):
                    for b in range(batch):
                        total = 0.0
                        for m in range(n_y):
                            total += K[i, m, b] * H[m, j, b]
                        I_KH[i, j, b] = (1.0 if i == j else 0.0) - total
            matmul(I_KH, P, I_KHP)
            matmul_transposed(I_KHP, I_KH, FP)
            matmul(K, R_used, KR)
            matmul_transposed(KR, K, I_KHP)
            add(FP, I_KHP)
            for i in range(n):
                for j in range(n):
                    for b in range(batch):
                        if measured[b]:
                            P[i, j, b] = FP[i, j, b]
        _record(x, alive, k, out)


@numba.njit(cache=True)
def _sigma_points(x, P, spread, scaled, root, definite, out):
    """Merwe's ``2 n + 1`` sigma points of ``(x, P)`` into ``out: (2 n + 1, n, batch)``
    (filterpy's order: ``x``, ``x + U[k]``, ``x - U[k]`` with ``U^T U = spread P``);
    ``definite[b]`` False where ``spread P`` is not positive definite."""
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            for b in range(x.shape[1]):
                scaled[i, j, b] = spread * P[i, j, b]
    upper_cholesky(scaled, root)
    positive_definite(root, definite)
    out[0] = x
    for k in range(n):
        for i in range(n):
            for b in range(x.shape[1]):
                out[k + 1, i, b] = x[i, b] - -root[k, i, b]
                out[n + k + 1, i, b] = x[i, b] - root[k, i, b]


@numba.njit(cache=True)
def _unscented_transform(points, Wm, Wc, noise, mean, covariance, residuals):
    """filterpy's ``unscented_transform`` for every trajectory: ``mean = Wm @ points``,
    ``covariance = residuals^T diag(Wc) residuals + noise`` (``points: (count, n, batch)``,
    ``noise: (n, n, batch)``)."""
    count, n, batch = points.shape
    for j in range(n):
        for b in range(batch):
            total = 0.0
            for i in range(count):
                total += Wm[i] * points[i, j, b]
            mean[j, b] = total
    for i in range(count):
        for j in range(n):
            for b in range(batch):
                residuals[i, j, b] = points[i, j, b] - mean[j, b]
    for a in range(n):
        for c in range(n):
            for b in range(batch):
                total = 0.0
                for i in range(count):
                    total += residuals[i, a, b] * (Wc[i] * residuals[i, c, b])
                covariance[a, c, b] = total + noise[a, c, b]


@numba.njit(cache=True)
def _stop_where(alive, ok):
    """Trajectories where ``ok`` is False stop (``alive[b] = False``)."""
    for b in range(alive.shape[0]):
        alive[b] = alive[b] and ok[b]


@numba.njit  # disk-cached once bound to a model: kernel_cache.bind
def ukf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, Wm, Wc, spread, inflation, threshold, out,
):  # fmt: skip
    """filterpy's ``UnscentedKalmanFilter`` with Merwe scaled sigma points (``Wm, Wc``,
    ``spread = n + lambda``) and the RK4 transition (``estimators/filters/ukf.py``): predict
    through the sigma points (each then constrained), inflate ``P = inflation (P - Q) +
    Q``, then redraw them from the predicted ``(x, P)``; update ``K = Pxz S^-1``, ``P = P
    - K S K^T``, with ``R`` Huber's (:func:`_huber_noise`) for a finite ``threshold``."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    count = 2 * n + 1
    x, P, u_previous = np.empty((n, batch)), np.empty((n, n, batch)), np.empty(batch)
    scaled, root = np.empty((n, n, batch)), np.empty((n, n, batch))
    points, propagated = np.empty((count, n, batch)), np.empty((count, n, batch))
    residuals_x, work = np.empty((count, n, batch)), np.empty((5, n, batch))
    outputs, residuals_z = np.empty((count, n_y, batch)), np.empty((count, n_y, batch))
    zp, S, SI = np.empty((n_y, batch)), np.empty((n_y, n_y, batch)), np.empty((n_y, n_y, batch))
    Pxz, K, KS = np.empty((n, n_y, batch)), np.empty((n, n_y, batch)), np.empty((n, n_y, batch))
    Q_each, R_each, R_used = (
        np.empty((n, n, batch)),
        np.empty((n_y, n_y, batch)),
        np.empty((n_y, n_y, batch)),
    )
    innovation = np.empty((n_y, batch))
    alive, measured, ok = (
        np.ones(batch, np.bool_),
        np.empty(batch, np.bool_),
        np.empty(batch, np.bool_),
    )
    robust = math.isfinite(threshold)
    broadcast(Q, Q_each)
    broadcast(R, R_each)
    for i in range(n):
        x[i, :] = x0[i]
    broadcast(P0, P)
    _sigma_points(x, P, spread, scaled, root, ok, propagated)
    _stop_where(alive, ok)
    for k in range(steps):
        if k > 0:
            for b in range(batch):
                u_previous[b] = u[b, k - 1]
            _sigma_points(x, P, spread, scaled, root, ok, points)
            _stop_where(alive, ok)
            for i in range(count):
                rk4_step(drift, p, g, points[i], u_previous, dt, propagated[i], work)
                constrain(propagated[i], p)
            _unscented_transform(propagated, Wm, Wc, Q_each, x, P, residuals_x)
            if inflation != 1.0:
                inflate(P, Q, inflation)
            _sigma_points(x, P, spread, scaled, root, ok, propagated)
            _stop_where(alive, ok)
        if _measured_now(y, k, alive, measured):
            for i in range(count):
                sensed_output(output, sense, q, s, propagated[i], outputs[i])
            _unscented_transform(outputs, Wm, Wc, R_each, zp, S, residuals_z)
            if robust:
                for c in range(n_y):
                    for b in range(batch):
                        innovation[c, b] = y[b, k, c] - zp[c, b]
                _huber_noise(R, innovation, S, threshold, R_used)
                _unscented_transform(outputs, Wm, Wc, R_used, zp, S, residuals_z)
            invert_each(S, SI, ok)
            _stop_singular(alive, measured, ok)
            Pxz[:, :, :] = 0.0
            for i in range(count):
                for a in range(n):
                    for c in range(n_y):
                        for b in range(batch):
                            dx = propagated[i, a, b] - x[a, b]
                            Pxz[a, c, b] += Wc[i] * (dx * (outputs[i, c, b] - zp[c, b]))
            matmul(Pxz, SI, K)
            for a in range(n):
                for b in range(batch):
                    correction = 0.0
                    for c in range(n_y):
                        correction += K[a, c, b] * (y[b, k, c] - zp[c, b])
                    if measured[b]:
                        x[a, b] = x[a, b] + correction
            matmul(K, S, KS)
            for a in range(n):
                for c in range(n):
                    for b in range(batch):
                        total = 0.0
                        for m in range(n_y):
                            total += KS[a, m, b] * K[c, m, b]
                        if measured[b]:
                            P[a, c, b] = P[a, c, b] - total
        _record(x, alive, k, out)
