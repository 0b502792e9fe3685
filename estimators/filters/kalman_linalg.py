"""The small dense linear algebra the compiled EKF and UKF kernels share (numba, in place):
inverses, Cholesky factors, products and broadcasts."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def invert(matrix, out):
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
def invert_each(matrices, out, invertible):
    """``out[:, :, b] = matrices[:, :, b]^-1`` for every trajectory ``b`` of
    ``matrices: (m, m, batch)``; ``invertible[b]`` False where it is singular."""
    m, batch = matrices.shape[0], matrices.shape[2]
    if m == 1:
        for b in range(batch):
            invertible[b] = matrices[0, 0, b] != 0.0
            out[0, 0, b] = 1.0 / matrices[0, 0, b] if invertible[b] else 0.0
        return
    matrix, inverse = np.empty((m, m)), np.empty((m, m))
    for b in range(batch):
        matrix[:, :] = matrices[:, :, b]
        invertible[b] = invert(matrix, inverse)
        out[:, :, b] = inverse


@numba.njit(cache=True)
def upper_cholesky(matrix, out):
    """``out[:, :, b]`` upper triangular with ``out^T out = matrix[:, :, b]`` for every
    trajectory (scipy's ``cholesky``, what filterpy's sigma points use); where
    ``matrix[:, :, b]`` is not positive definite, a diagonal entry of ``out[:, :, b]`` is
    NaN (:func:`positive_definite`)."""
    n, batch = matrix.shape[0], matrix.shape[2]
    out[:, :, :] = 0.0
    for j in range(n):
        for b in range(batch):
            diagonal = matrix[j, j, b]
            for k in range(j):
                diagonal -= out[k, j, b] * out[k, j, b]
            out[j, j, b] = math.sqrt(diagonal) if diagonal > 0.0 else math.nan
        for i in range(j + 1, n):
            for b in range(batch):
                total = matrix[j, i, b]
                for k in range(j):
                    total -= out[k, j, b] * out[k, i, b]
                out[j, i, b] = total / out[j, j, b]


@numba.njit(cache=True)
def positive_definite(root, definite):
    """``definite[b]``: the Cholesky factor ``root[:, :, b]`` (:func:`upper_cholesky`)
    exists, its diagonal free of NaN."""
    definite[:] = True
    for j in range(root.shape[0]):
        for b in range(root.shape[2]):
            definite[b] = definite[b] and not math.isnan(root[j, j, b])


@numba.njit(inline="always")
def matmul(a, b, out):
    """``out = a @ b`` for every trajectory (``a: (i, m, batch)``, ``b: (m, j, batch)``).
    Indexed whole, without views: a view costs reference counting, more than these small
    products' arithmetic."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            for lane in range(out.shape[2]):
                out[i, j, lane] = 0.0
            for m in range(a.shape[1]):
                for lane in range(out.shape[2]):
                    out[i, j, lane] += a[i, m, lane] * b[m, j, lane]


@numba.njit(inline="always")
def matmul_transposed(a, b, out):
    """``out = a @ b^T`` for every trajectory (``a: (i, m, batch)``, ``b: (j, m, batch)``)."""
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            for lane in range(out.shape[2]):
                out[i, j, lane] = 0.0
            for m in range(a.shape[1]):
                for lane in range(out.shape[2]):
                    out[i, j, lane] += a[i, m, lane] * b[j, m, lane]


@numba.njit(inline="always")
def add(a, b):
    """``a += b`` for arrays of one shape ``(i, j, batch)``."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            for lane in range(a.shape[2]):
                a[i, j, lane] += b[i, j, lane]


@numba.njit(inline="always")
def add_each(a, matrix):
    """``a[:, :, b] += matrix`` for every trajectory ``b``."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            value = matrix[i, j]
            for lane in range(a.shape[2]):
                a[i, j, lane] += value


@numba.njit(inline="always")
def broadcast(matrix, out):
    """``out[:, :, b] = matrix`` for every trajectory."""
    for i in range(matrix.shape[0]):
        for j in range(matrix.shape[1]):
            out[i, j, :] = matrix[i, j]


@numba.njit(inline="always")
def inflate(P, Q, inflation):
    """``P = inflation (P - Q) + Q`` for every trajectory."""
    for i in range(P.shape[0]):
        for j in range(P.shape[1]):
            noise = Q[i, j]
            for lane in range(P.shape[2]):
                P[i, j, lane] = inflation * (P[i, j, lane] - noise) + noise
