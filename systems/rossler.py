"""Rossler system: ``dx1 = -x2 - x3 + u``, ``dx2 = x1 + a x2``, ``dx3 = b + x3 (x1 - c)``, ``y = x2``."""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("rossler")
class Rossler(MeasureOneState):
    name = "rossler"
    state_names = ("x1", "x2", "x3")
    g = np.array([1.0, 0.0, 0.0])
    x0_low = np.array([-15.0, -15.0, 0.0])
    x0_high = np.array([15.0, 15.0, 1.0])
    measured = 1

    def __init__(self, a: float = 0.1, b: float = 0.1, c: float = 14.0) -> None:
        self.a, self.b, self.c = a, b, c

    def params(self):
        return {"a": self.a, "b": self.b, "c": self.c}

    def constrain(self, x):
        """Reflect ``x3`` at 0 (erratum E1).

        ``x3 >= 0`` is forward invariant for the noise-free flow (``dx3/dt = b > 0``
        at ``x3 = 0``), but additive process noise of 0.01 pushes ``x3``, which
        sits near ``b / (c - x1) ~ 0.007``, below 0; once ``x1 > c`` a negative
        ``x3`` grows without bound and the trajectory escapes to infinity (4 of
        the 80 standard Rossler test trajectories of the unamended protocol).
        """
        reflected = x.copy()
        reflected[..., 2] = np.abs(x[..., 2])
        return reflected

    def f(self, x):
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        return stack([-x2 - x3, x1 + self.a * x2, self.b + x3 * (x1 - self.c)])

    def f_jacobian(self, x):
        x1, x3 = x[..., 0], x[..., 2]
        jacobian = np.zeros((*x.shape, 3))
        jacobian[..., 0, 1] = -1.0
        jacobian[..., 0, 2] = -1.0
        jacobian[..., 1, 0] = 1.0
        jacobian[..., 1, 1] = self.a
        jacobian[..., 2, 0] = x3
        jacobian[..., 2, 2] = x1 - self.c
        return jacobian

    def compiled(self):
        return measured_states(
            [self.measured], self.g, [self.a, self.b, self.c], _drift, _drift_jacobian,
            constrain=_reflect, drift_flops=7, jacobian_flops=1, jacobian_nonzeros=6,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    for j in range(x.shape[1]):
        x1, x2, x3 = x[0, j], x[1, j], x[2, j]
        out[0, j] = -x2 - x3
        out[1, j] = x1 + p[0] * x2
        out[2, j] = p[1] + x3 * (x1 - p[2])


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    out[:, :, :] = 0.0
    for j in range(x.shape[1]):
        out[0, 1, j] = -1.0
        out[0, 2, j] = -1.0
        out[1, 0, j] = 1.0
        out[1, 1, j] = p[0]
        out[2, 0, j] = x[2, j]
        out[2, 2, j] = x[0, j] - p[2]


@numba.njit(cache=True)
def _reflect(x, p):
    for j in range(x.shape[1]):
        x[2, j] = abs(x[2, j])
