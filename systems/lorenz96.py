"""Lorenz-96 with ``n`` states, forcing ``F = 8``, input into the first state.

``dx_i = (x_{i+1} - x_{i-2}) x_{i-1} - x_i + F (+ u for i = 0)``, indices
modulo ``n`` (Lorenz, "Predictability: a problem partly solved", 1996). Every
other state is measured, ``y = (x_0, x_2, x_4, ...)``: the usual sparse
observation of data assimilation studies, which keeps the system observable
(each unmeasured ``x_i`` enters the derivative of a measured neighbour). The
initial box ``[F - 1, F + 1]^n`` surrounds the unstable equilibrium ``x_i = F``,
as the paper's Lorenz box surrounds the origin; trajectories leave it for the
chaotic attractor within seconds.

The states sit on a ring (``System.ring``: one state per site, the outputs at
the even sites), which a local observer can use. The dimension is part of the name: ``lorenz96-n5``, ``-n10``, ``-n20`` and
``-n40``, ``-n80`` and ``-n160`` are registered (:func:`lorenz96` makes any other size).
"""

from __future__ import annotations

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import Ring, System
from kkl_bench.registry import systems

FORCING = 8.0
SIZES = (5, 10, 20, 40, 80, 160)
"""The registered dimensions (the scaling study's)."""


class Lorenz96(System):
    """Lorenz-96 of dimension ``len(state_names)``; use :func:`lorenz96` for a sized class."""

    def __init__(self, forcing: float = FORCING) -> None:
        self.forcing = forcing
        index = np.arange(self.n_x)
        # index arrays, not lists: numpy and torch index with them several times faster
        self._next, self._before, self._previous = (
            (index + shift) % self.n_x for shift in (1, -2, -1)
        )

    def params(self):
        return {"n": self.n_x, "F": self.forcing}

    def with_sites(self, sites: int) -> Lorenz96:
        return lorenz96(sites)(self.forcing)

    def f(self, x):
        advection = (x[..., self._next] - x[..., self._before]) * x[..., self._previous]
        return advection - x + self.forcing

    def h(self, x):
        return x[..., self.measured]

    def f_jacobian(self, x):
        n = self.n_x
        rows = np.arange(n)
        jacobian = np.zeros((*x.shape, n))
        jacobian[..., rows, rows] = -1.0
        jacobian[..., rows, self._next] += x[..., self._previous]
        jacobian[..., rows, self._before] -= x[..., self._previous]
        jacobian[..., rows, self._previous] += x[..., self._next] - x[..., self._before]
        return jacobian

    def h_jacobian(self, x):
        jacobian = np.zeros((*x.shape[:-1], self.n_y, self.n_x))
        jacobian[..., np.arange(self.n_y), self.measured] = 1.0
        return jacobian

    def compiled(self):
        n = self.n_x  # each row of df/dx has 4 nonzeros: the diagonal and 3 neighbours
        return measured_states(
            self.measured, self.g, [self.forcing], _drift, _drift_jacobian,
            drift_flops=4 * n, jacobian_flops=2 * n, jacobian_nonzeros=4 * n,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    n = x.shape[0]
    for i in range(n):
        following, before, previous = (i + 1) % n, (i - 2) % n, (i - 1) % n
        for j in range(x.shape[1]):
            advection = (x[following, j] - x[before, j]) * x[previous, j]
            out[i, j] = advection - x[i, j] + p[0]


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    n = x.shape[0]
    out[:, :, :] = 0.0
    for i in range(n):
        following, before, previous = (i + 1) % n, (i - 2) % n, (i - 1) % n
        for j in range(x.shape[1]):
            out[i, i, j] = -1.0
            out[i, following, j] = x[previous, j]
            out[i, before, j] = -x[previous, j]
            out[i, previous, j] = x[following, j] - x[before, j]


def lorenz96(n: int) -> type[Lorenz96]:
    """The Lorenz-96 system class of dimension ``n`` (at least 4), named ``lorenz96-n<n>``."""
    if n < 4:
        raise ValueError(f"Lorenz-96 needs at least 4 states, got n = {n}")
    g = np.zeros(n)
    g[0] = 1.0
    attributes = {
        "name": f"lorenz96-n{n}",
        "state_names": tuple(f"x{i}" for i in range(n)),
        "g": g,
        "x0_low": np.full(n, FORCING - 1.0),
        "x0_high": np.full(n, FORCING + 1.0),
        "measured": np.arange(0, n, 2),
        "n_y": len(range(0, n, 2)),
        "ring": Ring(sites=n, output_sites=tuple(range(0, n, 2))),
        "__doc__": f"Lorenz-96 with {n} states, every other one measured.",
    }
    return type(f"Lorenz96N{n}", (Lorenz96,), attributes)


Lorenz96N5, Lorenz96N10, Lorenz96N20, Lorenz96N40, Lorenz96N80, Lorenz96N160 = (
    systems.register(f"lorenz96-n{n}")(lorenz96(n)) for n in SIZES
)
