"""Lorenz system: ``dx1 = p (x2 - x1) + u``, ``dx2 = x1 (q - x3) - x2``, ``dx3 = x1 x2 - r x3``, ``y = x2``."""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("lorenz")
class Lorenz(MeasureOneState):
    name = "lorenz"
    state_names = ("x1", "x2", "x3")
    g = np.array([1.0, 0.0, 0.0])
    x0_low = np.array([-1.0, -1.0, -1.0])
    x0_high = np.array([1.0, 1.0, 1.0])
    measured = 1

    def __init__(self, p: float = 10.0, q: float = 28.0, r: float = 8.0 / 3.0) -> None:
        self.p, self.q, self.r = p, q, r

    def params(self):
        return {"p": self.p, "q": self.q, "r": self.r}

    def f(self, x):
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        return stack([self.p * (x2 - x1), x1 * (self.q - x3) - x2, x1 * x2 - self.r * x3])

    def f_jacobian(self, x):
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        jacobian = np.zeros((*x.shape, 3))
        jacobian[..., 0, 0] = -self.p
        jacobian[..., 0, 1] = self.p
        jacobian[..., 1, 0] = self.q - x3
        jacobian[..., 1, 1] = -1.0
        jacobian[..., 1, 2] = -x1
        jacobian[..., 2, 0] = x2
        jacobian[..., 2, 1] = x1
        jacobian[..., 2, 2] = -self.r
        return jacobian

    def compiled(self):
        return measured_states(
            [self.measured], self.g, [self.p, self.q, self.r], _drift, _drift_jacobian,
            drift_flops=8, jacobian_flops=2, jacobian_nonzeros=8,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    for j in range(x.shape[1]):
        x1, x2, x3 = x[0, j], x[1, j], x[2, j]
        out[0, j] = p[0] * (x2 - x1)
        out[1, j] = x1 * (p[1] - x3) - x2
        out[2, j] = x1 * x2 - p[2] * x3


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    for j in range(x.shape[1]):
        x1, x2, x3 = x[0, j], x[1, j], x[2, j]
        out[0, 0, j] = -p[0]
        out[0, 1, j] = p[0]
        out[0, 2, j] = 0.0
        out[1, 0, j] = p[1] - x3
        out[1, 1, j] = -1.0
        out[1, 2, j] = -x1
        out[2, 0, j] = x2
        out[2, 1, j] = x1
        out[2, 2, j] = -p[2]
