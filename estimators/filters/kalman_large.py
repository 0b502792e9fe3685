"""The EKF and the UKF of large systems compiled: one trajectory at a time, on BLAS.

:func:`kalman_kernels.ekf` keeps the batch on the last axis of every matrix, which pays
at a few states (each operation one loop over the batch) and costs at many: its products
of two ``(n, n, batch)`` arrays stride through more memory than a cache holds at
``n = 160`` and spend ``2 n^3`` flops each where a stage Jacobian of Lorenz-96 has ``4 n``
nonzeros. :func:`ekf` runs the same filter (predict ``x = C(RK4(x))``, ``P = F P F^T + Q``
with the same inflation, the update in Joseph form, Huber's noise, the same stops) on one
trajectory at a time with dense ``(n, n)`` matrices, and takes the structure the model
offers:

- each product with a sparse factor (a stage Jacobian in the chain rule, the RK4 step's
  Jacobian ``F``, the output's Jacobian ``H``) runs over the factor's nonzeros, found row
  by row at every step, as sums of contiguous rows;
- the update's dense products (``K (H P)``, ``(C H^T) K^T``, ``K R K^T``) and the
  innovation covariance's inverse run on BLAS and LAPACK (numpy's, through numba);
- the Joseph form is written with ``H`` on the outside,
  ``C = P - K (H P)``, ``P = C - (C H^T) K^T + K R K^T``, which equals
  ``(I - K H) P (I - K H)^T + K R K^T`` without forming ``I - K H``.

:func:`kalman_kernels.ukf` sums over the ``2 n + 1`` sigma points in its innermost loop,
striding through ``(2 n + 1, n, batch)`` arrays: at ``n = 160`` it was 1.6 times slower
than filterpy's UKF on numpy. :func:`ukf` runs the same filter one trajectory at a time
with the sigma points as the columns of an ``(n, 2 n + 1)`` array, which the model's
functions sweep as they sweep a batch; the square root is LAPACK's Cholesky factor and
every sum over the sigma points (``P``, ``S``, ``P_xz``) and the gain's products are BLAS
products.

The estimates equal the reference engine's to rounding (the association of the products
differs; ``tests/test_filter_engines.py``). Shapes as in :mod:`kalman_kernels`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from kkl_bench.estimators.filters.kalman_kernels import (
    _huber_noise,
    _sensed_output_jacobian,
    all_finite,
)

from kkl_bench.protocol.compiled import (
    CompiledModel,
    _stage_point,
    rk4_step,
    sensed_output,
    vector_field,
)


@numba.njit(cache=True)
def _nonzeros(matrix, columns, counts):
    """``columns[i, :counts[i]]``: the columns of row ``i``'s nonzeros in ``matrix (r, c)``,
    in ascending order."""
    for i in range(matrix.shape[0]):
        count = 0
        for j in range(matrix.shape[1]):
            if matrix[i, j] != 0.0:
                columns[i, count] = j
                count += 1
        counts[i] = count


@numba.njit(cache=True)
def _sparse_times(a, columns, counts, b, out):
    """``out = a @ b`` over ``a``'s nonzeros (:func:`_nonzeros`): row ``i`` of ``out`` is
    the sum of ``b``'s rows ``c`` times ``a[i, c]``, in ascending ``c``."""
    out[:, :] = 0.0
    for i in range(a.shape[0]):
        for k in range(counts[i]):
            column = columns[i, k]
            value = a[i, column]
            for j in range(b.shape[1]):
                out[i, j] += value * b[column, j]


@numba.njit(cache=True)
def _times_sparse_transposed(a, b, columns, counts, out):
    """``out = a @ b^T`` over ``b``'s nonzeros: ``out[i, j]`` sums ``a[i, c] b[j, c]``."""
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            total = 0.0
            for k in range(counts[j]):
                column = columns[j, k]
                total += a[i, column] * b[j, column]
            out[i, j] = total


@numba.njit(inline="always")
def _chain(jacobian, previous, scale, target, factor, columns, counts):
    """``target = J (I + scale previous)`` (:func:`kkl_bench.protocol.compiled._chain`) over
    the stage Jacobian's nonzeros; ``jacobian: (n, n)``, ``factor: (n, n)`` scratch."""
    n = jacobian.shape[0]
    for k in range(n):
        for j in range(n):
            factor[k, j] = (1.0 if k == j else 0.0) + scale * previous[k, j]
    _nonzeros(jacobian, columns, counts)
    _sparse_times(jacobian, columns, counts, factor, target)


@numba.njit
def _step_jacobian(drift, drift_jacobian, p, g, x, u, dt, out, work, stage_jacobian, dk, factor, columns, counts):  # fmt: skip
    """``out (n, n)``: the Jacobian of the RK4 step at the point ``x (n, 1)`` by the chain
    rule (:func:`kkl_bench.protocol.compiled.rk4_step_jacobian`), each stage's product over
    its Jacobian's nonzeros. ``work: (5, n, 1)``, ``stage_jacobian: (n, n, 1)``, ``dk: (4,
    n, n)``, ``factor: (n, n)`` scratch."""
    k, stage = work[0], work[4]
    half = 0.5 * dt
    vector_field(drift, p, g, x, u, k)
    drift_jacobian(x, p, stage_jacobian)
    dk[0] = stage_jacobian[:, :, 0]
    for index, scale in enumerate((half, half, dt)):
        _stage_point(x, k, scale, stage)
        if index < 2:
            vector_field(drift, p, g, stage, u, k)
        drift_jacobian(stage, p, stage_jacobian)
        _chain(stage_jacobian[:, :, 0], dk[index], scale, dk[index + 1], factor, columns, counts)
    sixth = dt / 6.0
    n = x.shape[0]
    for i in range(n):
        for j in range(n):
            identity = 1.0 if i == j else 0.0
            out[i, j] = identity + sixth * (
                dk[0, i, j] + 2.0 * dk[1, i, j] + 2.0 * dk[2, i, j] + dk[3, i, j]
            )


@numba.njit(inline="always")
def _with_noise_inverted(S, R, residual, threshold, S3, R_used):
    """Adds the measurement noise to the innovation covariance ``S (n_y, n_y)`` in place
    (``R``, or Huber's ``R_used`` for a finite ``threshold``, from the ``residual (n_y,
    1)``; ``S3, R_used: (n_y, n_y, 1)`` scratch) and returns ``(S^-1, True)``, or ``(empty,
    False)`` where ``S`` is singular (LAPACK's ``getrf`` finds a zero pivot, as numpy's
    ``inv`` does)."""
    if math.isfinite(threshold):
        S3[:, :, 0] = S + R
        _huber_noise(R, residual, S3, threshold, R_used)
    else:
        R_used[:, :, 0] = R
    S += R_used[:, :, 0]
    inverse, invertible = np.asfortranarray(np.empty((0, 0))), True  # inv's layout
    try:
        inverse = np.linalg.inv(S)
    except Exception:
        invertible = False
    return inverse, invertible


@numba.njit  # disk-cached once bound to a model: kernel_cache.bind
def ekf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, inflation, threshold, out,
):  # fmt: skip
    """:func:`kalman_kernels.ekf`'s filter, one trajectory at a time (the module docstring)."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    x, x_next, u_previous = np.empty((n, 1)), np.empty((n, 1)), np.empty(1)
    work, stage_jacobian = np.empty((5, n, 1)), np.empty((n, n, 1))
    dk, factor = np.empty((4, n, n)), np.empty((n, n))
    F, P, FP, PF = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    columns, counts = np.empty((n, n), np.int64), np.empty(n, np.int64)
    H3, h, slope = np.empty((n_y, n, 1)), np.empty((n_y, 1)), np.empty((n_y, 1))
    H, HP, S = np.empty((n_y, n)), np.empty((n_y, n)), np.empty((n_y, n_y))
    CH = np.empty((n, n_y))
    h_columns, h_counts = np.empty((n_y, n), np.int64), np.empty(n_y, np.int64)
    S3, R_used = np.empty((n_y, n_y, 1)), np.empty((n_y, n_y, 1))
    for b in range(batch):
        x[:, 0] = x0
        P[:, :] = P0
        for k in range(steps):
            if k > 0:
                u_previous[0] = u[b, k - 1]
                _step_jacobian(drift, drift_jacobian, p, g, x, u_previous, dt, F, work, stage_jacobian, dk, factor, columns, counts)  # fmt: skip
                rk4_step(drift, p, g, x, u_previous, dt, x_next, work)
                constrain(x_next, p)
                x[:, :] = x_next
                _nonzeros(F, columns, counts)
                _sparse_times(F, columns, counts, P, FP)
                PF[:, :] = FP.T  # (F P)^T = P F^T, P symmetric
                _sparse_times(F, columns, counts, PF, P)
                P += Q
                if inflation != 1.0:
                    P[:, :] = inflation * (P - Q) + Q
            if all_finite(y[b, k]):
                _sensed_output_jacobian(output, output_jacobian, sense_slope, q, s, x, h, slope, H3)  # fmt: skip
                H[:, :] = H3[:, :, 0]
                _nonzeros(H, h_columns, h_counts)
                _sparse_times(H, h_columns, h_counts, P, HP)
                _times_sparse_transposed(HP, H, h_columns, h_counts, S)
                sensed_output(output, sense, q, s, x, h)
                for j in range(n_y):
                    h[j, 0] = y[b, k, j] - h[j, 0]
                SI, invertible = _with_noise_inverted(S, R, h, threshold, S3, R_used)
                if not invertible:
                    break  # the trajectory stops before this sample
                K = np.dot(np.ascontiguousarray(HP.T), np.ascontiguousarray(SI))  # P H^T S^-1
                for i in range(n):
                    correction = 0.0
                    for j in range(n_y):
                        correction += K[i, j] * h[j, 0]
                    x[i, 0] = x[i, 0] + correction
                C = P - np.dot(K, HP)
                _times_sparse_transposed(C, H, h_columns, h_counts, CH)
                KR = np.dot(K, np.ascontiguousarray(R_used[:, :, 0]))
                P[:, :] = C - np.dot(CH, K.T) + np.dot(KR, K.T)
            out[b, k, :] = x[:, 0]
            if not all_finite(x[:, 0]):
                break


@numba.njit(inline="always")
def _sigma_points(x, P, spread, out):
    """Merwe's ``2 n + 1`` sigma points of ``(x (n,), P (n, n))`` as the columns of ``out (n,
    2 n + 1)``, in filterpy's order (``x``, ``x + U[k]``, ``x - U[k]`` with ``U^T U = spread
    P``: ``U[k]`` is column ``k`` of the lower factor, from LAPACK's ``potrf``); False where
    ``spread P`` is not positive definite."""
    n = x.shape[0]
    try:
        lower = np.linalg.cholesky(spread * P)
    except Exception:  # not positive definite, as scipy's cholesky finds
        return False
    for i in range(n):
        out[i, 0] = x[i]
        for k in range(n):
            out[i, k + 1] = x[i] - -lower[i, k]
            out[i, n + k + 1] = x[i] - lower[i, k]
    return True


@numba.njit(inline="always")
def _unscented_transform(points, Wm, Wc, mean, residuals):
    """``mean = points @ Wm`` and ``residuals = points - mean`` (``points: (size, 2 n + 1)``);
    returns ``residuals diag(Wc) residuals^T`` on BLAS (the noise is the caller's)."""
    mean[:] = np.dot(points, Wm)
    for i in range(points.shape[0]):
        for j in range(points.shape[1]):
            residuals[i, j] = points[i, j] - mean[i]
    return np.dot(residuals * Wc, np.ascontiguousarray(residuals.T))


@numba.njit  # disk-cached once bound to a model: kernel_cache.bind
def ukf(
    drift, drift_jacobian, output, output_jacobian, sense, sense_slope, constrain,
    p, q, s, g, y, u, dt, x0, P0, Q, R, Wm, Wc, spread, inflation, threshold, out,
):  # fmt: skip
    """:func:`kalman_kernels.ukf`'s filter, one trajectory at a time: the sigma points are
    the columns the model's functions sweep (``(n, 2 n + 1)``), the Cholesky factor comes
    from LAPACK and every sum over the sigma points (the covariances ``P``, ``S``, ``Pxz``)
    and the gain's products run on BLAS."""
    batch, steps, n_y = y.shape
    n = x0.shape[0]
    count = 2 * n + 1
    x, P = np.empty(n), np.empty((n, n))
    points, propagated = np.empty((n, count)), np.empty((n, count))
    residuals_x, work = np.empty((n, count)), np.empty((5, n, count))
    outputs, residuals_z = np.empty((n_y, count)), np.empty((n_y, count))
    zp, innovation = np.empty(n_y), np.empty((n_y, 1))
    S3, R_used = np.empty((n_y, n_y, 1)), np.empty((n_y, n_y, 1))
    u_previous = np.empty(count)
    for b in range(batch):
        x[:] = x0
        P[:, :] = P0
        if not _sigma_points(x, P, spread, propagated):
            continue  # the trajectory stops before its first sample
        for k in range(steps):
            if k > 0:
                u_previous[:] = u[b, k - 1]
                if not _sigma_points(x, P, spread, points):
                    break
                rk4_step(drift, p, g, points, u_previous, dt, propagated, work)
                constrain(propagated, p)
                P[:, :] = _unscented_transform(propagated, Wm, Wc, x, residuals_x) + Q
                if inflation != 1.0:
                    P[:, :] = inflation * (P - Q) + Q
                if not _sigma_points(x, P, spread, propagated):
                    break
            if all_finite(y[b, k]):
                sensed_output(output, sense, q, s, propagated, outputs)
                S = _unscented_transform(outputs, Wm, Wc, zp, residuals_z)
                for j in range(n_y):
                    innovation[j, 0] = y[b, k, j] - zp[j]
                SI, invertible = _with_noise_inverted(S, R, innovation, threshold, S3, R_used)
                if not invertible:
                    break  # the trajectory stops before this sample
                for i in range(n):
                    for j in range(count):
                        residuals_x[i, j] = propagated[i, j] - x[i]
                Pxz = np.dot(residuals_x * Wc, np.ascontiguousarray(residuals_z.T))
                K = np.dot(Pxz, SI)
                x += np.dot(K, innovation)[:, 0]
                P -= np.dot(np.dot(K, S), np.ascontiguousarray(K.T))
            out[b, k, :] = x
            if not all_finite(x):
                break


MIN_STATES = 20
"""Systems of this many states or more run :func:`ekf` and :func:`ukf`; fewer run the
batch-last kernels, which are cheaper there at 20 trajectories (Lorenz-96, µs a
trajectory-step at batch 20, batch-last against large: the EKF 0.82 against 4.75 at n = 5,
3.7 against 8.2 at n = 10, 24.4 against 17.7 at n = 20; the UKF 1.35 against 7.64, 5.8
against 15.6, 34.5 against 35.1, then 314 against 110 at n = 40 and 3464 against 398 at
n = 80; ``tests/benchmarks/test_large_filters.py``). The choice depends on the system
alone, so an estimate does not depend on the batch it is computed in."""


def takes(model: CompiledModel) -> bool:
    """Whether :func:`ekf` and :func:`ukf` run ``model`` (it has :data:`MIN_STATES` states
    or more)."""
    return model.n_x >= MIN_STATES


def flops_per_step(model: CompiledModel, nonzeros: tuple[int, int, int], robust: bool) -> int:
    """Flops of one trajectory-step of :func:`ekf` on ``model``, with ``nonzeros = (J, F,
    H)``: the nonzeros of a stage Jacobian, of the RK4 step's Jacobian and of the output's
    Jacobian (:func:`structural_nonzeros`), ``robust`` with Huber's noise."""
    n, m = model.n_x, model.n_y
    jacobian, step, output = nonzeros
    stages = 3 * (model.drift_flops + 4 * n) + 4 * model.jacobian_flops
    chain = 3 * (2 * n * n + 2 * jacobian * n) + 7 * n * n
    predict = model.step_flops + stages + chain + 4 * step * n + n * n  # F (F P)^T + Q
    innovation = 2 * output * n + 2 * output * m + m  # H P, (H P) H^T, the residual
    gain = 2 * m**3 + 2 * n * m * m + 2 * n * m + m * m  # S^-1, K, x + K r, S + R
    joseph = 2 * n * n * m + n * n + 2 * output * n + 2 * n * n * m + 2 * n * m * m
    joseph += 2 * n * n * m + 2 * n * n
    huber = 5 * m + m * m if robust else 0
    return predict + innovation + gain + joseph + huber


def structural_nonzeros(model: CompiledModel, seed: int = 0) -> tuple[int, int, int]:
    """``(J, F, H)``: the entries of a stage Jacobian ``df/dx``, of the RK4 step's Jacobian
    (the pattern of ``(I + J)^4``, the chain rule's products) and of the output's Jacobian
    that can be nonzero, read from the model's Jacobians at a random point (a structural
    zero is zero everywhere; any other entry is nonzero there with probability one)."""
    n = model.n_x
    point = np.random.default_rng(seed).standard_normal((n, 1))
    jacobian = np.empty((n, n, 1))
    model.drift_jacobian(point, model.p, jacobian)
    pattern = jacobian[:, :, 0] != 0.0
    step = np.eye(n, dtype=bool)
    for _ in range(4):
        step = step | (step.astype(np.int64) @ pattern.astype(np.int64) > 0)
    output = np.empty((model.n_y, n, 1))
    model.output_jacobian(point, model.q, output)
    return int(pattern.sum()), int(step.sum()), int(np.count_nonzero(output))
