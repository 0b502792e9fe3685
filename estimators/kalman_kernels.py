"""The EKF and the UKF compiled: the same arithmetic as filterpy's, without Python in the loop.

Each kernel runs a batch of trajectories through one filter with the protocol's
settings (``docs/protocol.md`` section 6) and the operations of filterpy's
``ExtendedKalmanFilter`` and ``UnscentedKalmanFilter`` (Merwe scaled sigma points,
Cholesky square root) in the same order, so its estimates equal the reference
engine's to rounding (``tests/test_filter_engines.py`` checks a relative 1e-9 on every
quick-profile cell of the paper and hard tracks). The model comes as a
:class:`~kkl_bench.protocol.compiled.CompiledModel`'s functions.

A trajectory whose innovation covariance is singular, or whose covariance is not
positive definite where the UKF needs its square root, stops there and keeps NaN for
the rest of its samples, as the reference engine does; so does one whose estimate
stops being finite (that estimate is kept).

Shapes: ``y: (batch, steps, n_y)`` (NaN where no measurement), ``u: (batch, steps)``,
``x0: (n_x,)``, ``P0, Q: (n_x, n_x)``, ``R: (n_y, n_y)``, ``out: (batch, steps, n_x)``
filled with NaN by the caller.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from kkl_bench.protocol.compiled import rk4_step, rk4_step_jacobian, sensed_output


@numba.njit(cache=True)
def _invert(matrix, out):
    """``out = matrix^-1`` by Gauss-Jordan elimination with partial pivoting; False if
    ``matrix`` is singular (a zero pivot, as LAPACK's ``getrf`` finds)."""
    n = matrix.shape[0]
    if n == 1:
        if matrix[0, 0] == 0.0:
            return False
        out[0, 0] = 1.0 / matrix[0, 0]
        return True
    work = matrix.copy()
    out[:, :] = 0.0
    for i in range(n):
        out[i, i] = 1.0
    for column in range(n):
        pivot = column
        for row in range(column + 1, n):
            if abs(work[row, column]) > abs(work[pivot, column]):
                pivot = row
        if work[pivot, column] == 0.0:
            return False
        for j in range(n):
            work[column, j], work[pivot, j] = work[pivot, j], work[column, j]
            out[column, j], out[pivot, j] = out[pivot, j], out[column, j]
        scale = 1.0 / work[column, column]
        for j in range(n):
            work[column, j] *= scale
            out[column, j] *= scale
        for row in range(n):
            if row != column:
                factor = work[row, column]
                for j in range(n):
                    work[row, j] -= factor * work[column, j]
                    out[row, j] -= factor * out[column, j]
    return True


@numba.njit(cache=True)
def _upper_cholesky(matrix, out):
    """``out`` upper triangular with ``out^T out = matrix`` (scipy's ``cholesky``, what
    filterpy's sigma points use); False if ``matrix`` is not positive definite."""
    n = matrix.shape[0]
    out[:, :] = 0.0
    for j in range(n):
        diagonal = matrix[j, j]
        for k in range(j):
            diagonal -= out[k, j] * out[k, j]
        if not diagonal > 0.0:
            return False
        out[j, j] = math.sqrt(diagonal)
        for i in range(j + 1, n):
            total = matrix[j, i]
            for k in range(j):
                total -= out[k, j] * out[k, i]
            out[j, i] = total / out[j, j]
    return True


@numba.njit(cache=True)
def _matmul(a, b, out):
    """``out = a @ b``."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            total = 0.0
            for m in range(a.shape[1]):
                total += a[i, m] * b[m, j]
            out[i, j] = total


@numba.njit(cache=True)
def all_finite(values):
    """Whether every entry of the one-dimensional ``values`` is finite."""
    for value in values:  # noqa: SIM110 (a loop numba compiles)
        if not math.isfinite(value):
            return False
    return True


@numba.njit  # not cached: numba cannot cache a function of functions
def _sensed_output_jacobian(output, output_jacobian, sense_slope, q, s, x, h, slope, out):
    """``out (n_y, n_x)`` = the Jacobian of ``s(h(x))``: the sensor's slope at ``h(x)``
    times ``dh/dx`` (:meth:`kkl_bench.measurement.SensedSystem.h_jacobian`)."""
    output(x, q, h)
    sense_slope(h, s, slope)
    output_jacobian(x, q, out)
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[j, i] = slope[j] * out[j, i]


@numba.njit(cache=True)
def _huber_noise(R, residual, S, threshold, out):
    """``out`` = ``R`` (diagonal) with each output's variance divided by its Huber weight
    ``min(1, threshold / e)``, ``e = |residual_j| / sqrt(S_jj)``
    (:func:`kkl_bench.estimators.kalman.huber_noise`, in the same operations)."""
    out[:, :] = 0.0
    for j in range(R.shape[0]):
        normalized = abs(residual[j]) / math.sqrt(S[j, j])
        weight = threshold / normalized if normalized > 0.0 else math.inf
        out[j, j] = R[j, j] / min(1.0, weight)


@numba.njit  # not cached: numba cannot cache a function of functions
def ekf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, inflation, threshold, out,
):  # fmt: skip
    """filterpy's ``ExtendedKalmanFilter`` with the RK4 transition (``estimators/ekf.py``):
    predict ``x = C(RK4(x))`` (``C`` the constraint), ``P = F P F^T + Q`` (``inflation
    (F P F^T) + Q`` with inflation), ``F`` the RK4 step's Jacobian at the posterior mean;
    update in Joseph form ``P = (I - K H) P (I - K H)^T + K R K^T``, with ``R`` Huber's
    (:func:`_huber_noise`) for a finite ``threshold``."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    x, x_next = np.empty(n), np.empty(n)
    P, F, FP = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    work, jacobian_work = np.empty((5, n)), np.empty((5, n, n))
    H, PHT, S, SI, K = (
        np.empty((n_y, n)),
        np.empty((n, n_y)),
        np.empty((n_y, n_y)),
        np.empty((n_y, n_y)),
        np.empty((n, n_y)),
    )
    KR, I_KH, I_KHP = np.empty((n, n_y)), np.empty((n, n)), np.empty((n, n))
    h, slope = np.empty(n_y), np.empty(n_y)
    robust = math.isfinite(threshold)
    R_used = R.copy()
    for b in range(batch):
        x[:] = x0
        P[:, :] = P0
        for k in range(steps):
            if k > 0:
                u_previous = u[b, k - 1]
                rk4_step_jacobian(
                    drift, drift_jacobian, p, g, x, u_previous, dt, F, work, jacobian_work
                )
                rk4_step(drift, p, g, x, u_previous, dt, x_next, work)
                constrain(x_next, p)
                x[:] = x_next
                _matmul(F, P, FP)
                _matmul(FP, F.T, P)
                for i in range(n):
                    for j in range(n):
                        P[i, j] += Q[i, j]
                if inflation != 1.0:
                    for i in range(n):
                        for j in range(n):
                            P[i, j] = inflation * (P[i, j] - Q[i, j]) + Q[i, j]
            if all_finite(y[b, k]):
                _sensed_output_jacobian(output, output_jacobian, sense_slope, q, s, x, h, slope, H)
                _matmul(P, H.T, PHT)
                _matmul(H, PHT, S)
                sensed_output(output, sense, q, s, x, h)
                for j in range(n_y):
                    h[j] = y[b, k, j] - h[j]
                if robust:
                    for i in range(n_y):
                        for j in range(n_y):
                            SI[i, j] = S[i, j] + R[i, j]
                    _huber_noise(R, h, SI, threshold, R_used)
                for i in range(n_y):
                    for j in range(n_y):
                        S[i, j] += R_used[i, j]
                if not _invert(S, SI):
                    break
                _matmul(PHT, SI, K)
                for i in range(n):
                    correction = 0.0
                    for j in range(n_y):
                        correction += K[i, j] * h[j]
                    x[i] = x[i] + correction
                for i in range(n):
                    for j in range(n):
                        total = 0.0
                        for m in range(n_y):
                            total += K[i, m] * H[m, j]
                        I_KH[i, j] = (1.0 if i == j else 0.0) - total
                _matmul(I_KH, P, I_KHP)
                _matmul(I_KHP, I_KH.T, P)
                _matmul(K, R_used, KR)
                _matmul(KR, K.T, FP)
                for i in range(n):
                    for j in range(n):
                        P[i, j] += FP[i, j]
            out[b, k] = x
            if not all_finite(x):
                break


@numba.njit(cache=True)
def _sigma_points(x, P, spread, root, out):
    """Merwe's ``2 n + 1`` sigma points of ``(x, P)`` into ``out`` (filterpy's order:
    ``x``, ``x + U[k]``, ``x - U[k]`` with ``U^T U = spread P``); False if ``spread P`` is
    not positive definite."""
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            root[i, j] = spread * P[i, j]
    if not _upper_cholesky(root.copy(), root):
        return False
    out[0] = x
    for k in range(n):
        for i in range(n):
            out[k + 1, i] = x[i] - -root[k, i]
            out[n + k + 1, i] = x[i] - root[k, i]
    return True


@numba.njit(cache=True)
def _unscented_transform(points, Wm, Wc, noise, mean, covariance, residuals):
    """filterpy's ``unscented_transform``: ``mean = Wm @ points``, ``covariance =
    residuals^T diag(Wc) residuals + noise``."""
    count, n = points.shape
    for j in range(n):
        total = 0.0
        for i in range(count):
            total += Wm[i] * points[i, j]
        mean[j] = total
    for i in range(count):
        for j in range(n):
            residuals[i, j] = points[i, j] - mean[j]
    for a in range(n):
        for c in range(n):
            total = 0.0
            for i in range(count):
                total += residuals[i, a] * (Wc[i] * residuals[i, c])
            covariance[a, c] = total + noise[a, c]


@numba.njit  # not cached: numba cannot cache a function of functions
def ukf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, Wm, Wc, spread, inflation, threshold, out,
):  # fmt: skip
    """filterpy's ``UnscentedKalmanFilter`` with Merwe scaled sigma points (``Wm, Wc``,
    ``spread = n + lambda``) and the RK4 transition (``estimators/ukf.py``): predict
    through the sigma points (each then constrained), inflate ``P = inflation (P - Q) +
    Q``, then redraw them from the predicted ``(x, P)``; update ``K = Pxz S^-1``, ``P = P
    - K S K^T``, with ``R`` Huber's (:func:`_huber_noise`) for a finite ``threshold``."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    count = 2 * n + 1
    x, P, root = np.empty(n), np.empty((n, n)), np.empty((n, n))
    points, propagated = np.empty((count, n)), np.empty((count, n))
    residuals_x, work = np.empty((count, n)), np.empty((5, n))
    outputs, residuals_z = np.empty((count, n_y)), np.empty((count, n_y))
    zp, S, SI = np.empty(n_y), np.empty((n_y, n_y)), np.empty((n_y, n_y))
    Pxz, K, KS = np.empty((n, n_y)), np.empty((n, n_y)), np.empty((n, n_y))
    robust = math.isfinite(threshold)
    R_used, innovation = R.copy(), np.empty(n_y)
    for b in range(batch):
        x[:] = x0
        P[:, :] = P0
        if not _sigma_points(x, P, spread, root, propagated):
            continue
        for k in range(steps):
            if k > 0:
                u_previous = u[b, k - 1]
                if not _sigma_points(x, P, spread, root, points):
                    break
                for i in range(count):
                    rk4_step(drift, p, g, points[i], u_previous, dt, propagated[i], work)
                    constrain(propagated[i], p)
                _unscented_transform(propagated, Wm, Wc, Q, x, P, residuals_x)
                if inflation != 1.0:
                    for i in range(n):
                        for j in range(n):
                            P[i, j] = inflation * (P[i, j] - Q[i, j]) + Q[i, j]
                if not _sigma_points(x, P, spread, root, propagated):
                    break
            if all_finite(y[b, k]):
                for i in range(count):
                    sensed_output(output, sense, q, s, propagated[i], outputs[i])
                _unscented_transform(outputs, Wm, Wc, R, zp, S, residuals_z)
                if robust:
                    for c in range(n_y):
                        innovation[c] = y[b, k, c] - zp[c]
                    _huber_noise(R, innovation, S, threshold, R_used)
                    _unscented_transform(outputs, Wm, Wc, R_used, zp, S, residuals_z)
                if not _invert(S, SI):
                    break
                Pxz[:, :] = 0.0
                for i in range(count):
                    for a in range(n):
                        dx = propagated[i, a] - x[a]
                        for c in range(n_y):
                            Pxz[a, c] += Wc[i] * (dx * (outputs[i, c] - zp[c]))
                _matmul(Pxz, SI, K)
                for a in range(n):
                    correction = 0.0
                    for c in range(n_y):
                        correction += K[a, c] * (y[b, k, c] - zp[c])
                    x[a] = x[a] + correction
                _matmul(K, S, KS)
                for a in range(n):
                    for c in range(n):
                        total = 0.0
                        for m in range(n_y):
                            total += KS[a, m] * K[c, m]
                        P[a, c] = P[a, c] - total
            out[b, k] = x
            if not all_finite(x):
                break
