"""Reverse Duffing oscillator: ``dx1 = a x2^3``, ``dx2 = -x1 + u``, ``y = x1`` (``a = 1``)."""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("duffing")
class ReverseDuffing(MeasureOneState):
    name = "duffing"
    state_names = ("x1", "x2")
    g = np.array([0.0, 1.0])
    x0_low = np.array([-1.0, -1.0])
    x0_high = np.array([1.0, 1.0])
    measured = 0

    def __init__(self, a: float = 1.0) -> None:
        self.a = a

    def params(self):
        return {"a": self.a}

    def f(self, x):
        x1, x2 = x[..., 0], x[..., 1]
        # a * x2 * x2 * x2 is bit-identical to x2 * x2 * x2 for a = 1
        return stack([self.a * x2 * x2 * x2, -x1])

    def f_jacobian(self, x):
        x2 = x[..., 1]
        jacobian = np.zeros((*x.shape, 2))
        jacobian[..., 0, 1] = 3.0 * self.a * x2 * x2
        jacobian[..., 1, 0] = -1.0
        return jacobian

    def compiled(self):
        return measured_states(
            [self.measured], self.g, [self.a], _drift, _drift_jacobian,
            drift_flops=4, jacobian_flops=3, jacobian_nonzeros=2,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    for j in range(x.shape[1]):
        x2 = x[1, j]
        out[0, j] = p[0] * x2 * x2 * x2
        out[1, j] = -x[0, j]


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    for j in range(x.shape[1]):
        out[0, 0, j] = 0.0
        out[0, 1, j] = 3.0 * p[0] * x[1, j] * x[1, j]
        out[1, 0, j] = -1.0
        out[1, 1, j] = 0.0
