"""The linear latent observer of a KKL observer, discretized exactly.

Between samples ``y`` is interpolated linearly (first-order hold), so one
matrix exponential gives the exact update

    z_{k+1} = Phi z_k + Gamma0 y_k + Gamma1 (y_{k+1} - y_k) / dt,

from the top block row ``[Phi, Gamma0, Gamma1]`` of
``expm(dt [[A, B, 0], [0, 0, I], [0, 0, 0]])``. An additive injection
``phi_k`` held over the step (zero-order hold) enters as
``A^{-1} (Phi - I) phi_k``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg import expm

from kkl_bench.measurement import held
from kkl_bench.support import flops


def spread_eigenvalues(n_z: int, slowest: float, fastest: float) -> np.ndarray:
    """``n_z`` distinct rates, geometrically spaced from ``slowest`` to ``fastest`` (1/s)."""
    if not 0 < slowest < fastest:
        raise ValueError(f"need 0 < slowest < fastest, got {slowest}, {fastest}")
    return np.geomspace(slowest, fastest, n_z)


def latent_matrices(rates: np.ndarray, n_y: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``A = -diag(rates)`` (Hurwitz) and ``B`` assigning latent mode ``i`` to output ``i mod n_y``.

    With one output ``B = 1``; with several, each output drives every
    ``n_y``-th mode, so each sees rates spread over the whole range. A diagonal
    ``A`` with distinct rates and a ``B`` without a zero row is controllable
    (Popov-Belevitch-Hautus test). Returns ``A: (n_z, n_z)`` and ``B: (n_z, n_y)``.
    """
    rates = np.asarray(rates, dtype=float)
    if np.any(rates <= 0) or len(np.unique(rates)) != len(rates):
        raise ValueError(f"latent rates must be distinct and positive, got {rates}")
    n_z = len(rates)
    b = np.zeros((n_z, n_y))
    b[np.arange(n_z), np.arange(n_z) % n_y] = 1.0
    return -np.diag(rates), b


class LatentObserver:
    """Exact sampled-data simulation of ``dz/dt = A z + B y + phi``, batched over trajectories.

    Parameters
    ----------
    a: ``(n_z, n_z)`` Hurwitz matrix.
    b: ``(n_z, n_y)`` input matrix.
    dt: sampling step (s).
    """

    def __init__(self, a: np.ndarray, b: np.ndarray, dt: float) -> None:
        n_z, n_y = b.shape
        block = np.zeros((n_z + 2 * n_y, n_z + 2 * n_y))
        block[:n_z, :n_z] = a
        block[:n_z, n_z : n_z + n_y] = b
        block[n_z : n_z + n_y, n_z + n_y :] = np.eye(n_y)
        top = expm(dt * block)[:n_z]
        self.a, self.b, self.dt = a, b, dt
        self.phi = top[:, :n_z]
        self.gamma0 = top[:, n_z : n_z + n_y]
        self.gamma1 = top[:, n_z + n_y :] / dt
        self.injection_gain = np.linalg.solve(a, self.phi - np.eye(n_z))
        # With a diagonal A (every built-in design) Phi and the injection gain are
        # diagonal too: the recursion is then elementwise, n_z times cheaper than a
        # matrix product (1620 times at Lorenz-96 n = 40), with the same numbers.
        self._diagonal = is_diagonal(a)

    @property
    def n_z(self) -> int:
        return self.a.shape[0]

    def initial_state(self, y0: np.ndarray) -> np.ndarray:
        """``z0 = -A^{-1} B y0``, the equilibrium for a frozen output. ``y0: (batch, n_y)``."""
        return -np.linalg.solve(self.a, self.b @ y0.T).T

    def run(
        self, y: np.ndarray, injection: Callable[[int, np.ndarray], np.ndarray] | None = None
    ) -> np.ndarray:
        """Latent trajectories ``(batch, steps, n_z)`` driven by ``y: (batch, steps, n_y)``;
        samples with no measurement (NaN) are driven by the last one, held
        (:func:`~kkl_bench.measurement.held`).

        ``injection(k, z_k)``, if given, returns ``phi_k: (batch, n_z)``, held
        over ``[t_k, t_{k+1})``; it sees only ``z_k`` (and whatever up to
        sample k its owner knows), so the recursion stays causal.
        """
        y = held(y)
        z = np.empty((y.shape[0], y.shape[1], self.n_z))
        z[:, 0] = self.initial_state(y[:, 0])
        drive = y[:, :-1] @ self.gamma0.T + np.diff(y, axis=1) @ self.gamma1.T
        batch, steps, n_y = y.shape
        flops.add(2 * flops.products(batch * (steps - 1), n_y, self.n_z))
        if self._diagonal:  # elementwise: not counted (kkl_bench.support.flops)
            phi, gain = np.diag(self.phi), np.diag(self.injection_gain)

            def apply(matrix: np.ndarray, v: np.ndarray) -> np.ndarray:
                return v * matrix
        else:
            phi, gain = self.phi, self.injection_gain
            products = (2 if injection is not None else 1) * (steps - 1)
            flops.add(products * flops.products(batch, self.n_z, self.n_z))

            def apply(matrix: np.ndarray, v: np.ndarray) -> np.ndarray:
                return v @ matrix.T

        for k in range(y.shape[1] - 1):
            z[:, k + 1] = apply(phi, z[:, k]) + drive[:, k]
            if injection is not None:
                z[:, k + 1] += apply(gain, injection(k, z[:, k]))
        return z


def is_diagonal(matrix) -> bool:
    """Whether a square numpy array or torch tensor has only zeros off its diagonal (one
    scan, no copy)."""
    if isinstance(matrix, np.ndarray):
        return np.count_nonzero(matrix) == np.count_nonzero(np.diagonal(matrix))
    return bool(matrix.count_nonzero() == matrix.diagonal().count_nonzero())


def latent_drift(z, a):
    """``A z`` for ``z: (..., n_z)`` (arrays or tensors), elementwise when ``A`` is diagonal."""
    if is_diagonal(a):
        return z * (np.diag(a) if isinstance(a, np.ndarray) else a.diagonal())
    return z @ a.T
