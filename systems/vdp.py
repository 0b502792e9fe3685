"""Van der Pol oscillator: ``dx1 = x2``, ``dx2 = mu (1 - x1^2) x2 - x1 + u``, ``y = x1``."""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("vdp")
class VanDerPol(MeasureOneState):
    name = "vdp"
    state_names = ("x1", "x2")
    g = np.array([0.0, 1.0])
    x0_low = np.array([-1.0, -1.0])
    x0_high = np.array([1.0, 1.0])
    measured = 0

    def __init__(self, mu: float = 3.0) -> None:
        self.mu = mu

    def params(self):
        return {"mu": self.mu}

    def f(self, x):
        x1, x2 = x[..., 0], x[..., 1]
        return stack([x2, self.mu * (1.0 - x1 * x1) * x2 - x1])

    def f_jacobian(self, x):
        x1, x2 = x[..., 0], x[..., 1]
        jacobian = np.zeros((*x.shape, 2))
        jacobian[..., 0, 1] = 1.0
        jacobian[..., 1, 0] = -2.0 * self.mu * x1 * x2 - 1.0
        jacobian[..., 1, 1] = self.mu * (1.0 - x1 * x1)
        return jacobian

    def compiled(self):
        return measured_states(
            [self.measured], self.g, [self.mu], _drift, _drift_jacobian,
            drift_flops=5, jacobian_flops=7, jacobian_nonzeros=3,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    for j in range(x.shape[1]):
        x1, x2 = x[0, j], x[1, j]
        out[0, j] = x2
        out[1, j] = p[0] * (1.0 - x1 * x1) * x2 - x1


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    for j in range(x.shape[1]):
        x1, x2 = x[0, j], x[1, j]
        out[0, 0, j] = 0.0
        out[0, 1, j] = 1.0
        out[1, 0, j] = -2.0 * p[0] * x1 * x2 - 1.0
        out[1, 1, j] = p[0] * (1.0 - x1 * x1)
