"""Batched RK4 simulation with a zero-order-hold input, process and measurement noise.

This module holds the only RK4 step of the project: the test sets, the
training-data generator and the model-based filters all call it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from kkl_bench.protocol.system import System


def rk4_step(system: System, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """One classical RK4 step of ``f(x) + g u`` with ``u`` held over all four stages.

    ``x: (..., n_x)``, ``u: (...)`` -> ``(..., n_x)``.
    """
    k1 = system.vector_field(x, u)
    k2 = system.vector_field(x + 0.5 * dt * k1, u)
    k3 = system.vector_field(x + 0.5 * dt * k2, u)
    k4 = system.vector_field(x + dt * k3, u)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rk4_step_jacobian(system: System, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """Jacobian of :func:`rk4_step` with respect to ``x``, by the chain rule.

    ``x: (..., n_x)``, ``u: (...)`` -> ``(..., n_x, n_x)``.
    """
    identity = np.eye(system.n_x)
    k1 = system.vector_field(x, u)
    dk1 = system.f_jacobian(x)
    x2 = x + 0.5 * dt * k1
    k2 = system.vector_field(x2, u)
    dk2 = system.f_jacobian(x2) @ (identity + 0.5 * dt * dk1)
    x3 = x + 0.5 * dt * k2
    k3 = system.vector_field(x3, u)
    dk3 = system.f_jacobian(x3) @ (identity + 0.5 * dt * dk2)
    dk4 = system.f_jacobian(x + dt * k3) @ (identity + dt * dk3)
    return identity + (dt / 6.0) * (dk1 + 2.0 * dk2 + 2.0 * dk3 + dk4)


def sha256_of_arrays(*arrays: np.ndarray) -> str:
    """First 16 hex digits of the SHA-256 of the arrays' float64 bytes, in order."""
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


@dataclass(frozen=True)
class Trajectories:
    """A batch of simulated trajectories on a shared time grid.

    Attributes
    ----------
    t: ``(steps,)`` sample times (s).
    u: ``(batch, steps, 1)`` held input samples ``u_k``.
    x: ``(batch, steps, n_x)`` true states.
    y: ``(batch, steps, n_y)`` noisy measurements.
    """

    t: np.ndarray
    u: np.ndarray
    x: np.ndarray
    y: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    def fingerprint(self) -> str:
        """:func:`sha256_of_arrays` of ``t, u, x, y``."""
        return sha256_of_arrays(self.t, self.u, self.x, self.y)


def simulate(
    system: System,
    x0: np.ndarray,
    u: np.ndarray,
    dt: float,
    process_noise: np.ndarray | None = None,
    measurement_noise: np.ndarray | None = None,
) -> Trajectories:
    """Simulate a batch: ``x_{k+1} = RK4(x_k, u_k) + w_k``, ``y_k = h(x_k) + v_k``.

    With process noise, ``x_{k+1}`` is passed through ``system.constrain``
    (erratum E1: Rossler's ``x3`` is reflected at 0).

    Parameters
    ----------
    x0: ``(batch, n_x)`` initial states.
    u: ``(batch, steps)`` input samples, held over each step.
    dt: step (s).
    process_noise: ``(batch, steps - 1, n_x)`` samples ``w_k``, or None for none.
    measurement_noise: ``(batch, steps, n_y)`` samples ``v_k``, or None for none.
    """
    x0 = np.asarray(x0, dtype=float)
    u = np.asarray(u, dtype=float)
    batch, steps = u.shape
    if x0.shape != (batch, system.n_x):
        raise ValueError(f"x0 has shape {x0.shape}; expected {(batch, system.n_x)} to match u")
    x = np.empty((batch, steps, system.n_x))
    x[:, 0] = x0
    for k in range(steps - 1):
        x[:, k + 1] = rk4_step(system, x[:, k], u[:, k], dt)
        if process_noise is not None:
            x[:, k + 1] = system.constrain(x[:, k + 1] + process_noise[:, k])
    y = system.h(x)
    if measurement_noise is not None:
        y = y + measurement_noise
    return Trajectories(t=dt * np.arange(steps), u=u[..., None], x=x, y=y)
