"""Chua's circuit in its double-scroll regime, input into the first state, ``y = x``.

``dx = alpha (y - x - phi(x)) + 0.3 u``, ``dy = x - y + z``, ``dz = -beta y`` with
the piecewise-linear diode ``phi(x) = m1 x + (m0 - m1) (|x + 1| - |x - 1|) / 2``
and ``alpha = 15.6``, ``beta = 28``, ``m0 = -8/7``, ``m1 = -5/7`` (Chua, Komuro
and Matsumoto, IEEE Trans. Circuits Syst. 33, 1986; the double scroll spans
about x in [-2.3, 2.3], y in [-0.4, 0.4], z in [-3.6, 3.6]). The initial box
is small and about the origin: a box covering the whole scroll sends about
half of its initial states to infinity (the truth itself escapes). The input
enters with gain 0.3: with gain 1, 12.6 % of the paper's square-wave inputs
(2000 draws from this box) push the state out of the scroll's basin and it
escapes too; with 0.5, 0.1 %; with 0.3, none (``docs/protocol.md`` section 8).
"""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("chua")
class Chua(MeasureOneState):
    name = "chua"
    state_names = ("x", "y", "z")
    input_gain = 0.3
    g = np.array([input_gain, 0.0, 0.0])
    x0_low = np.array([-0.5, -0.2, -0.5])
    x0_high = np.array([0.5, 0.2, 0.5])
    measured = 0

    def __init__(
        self,
        alpha: float = 15.6,
        beta: float = 28.0,
        m0: float = -8.0 / 7.0,
        m1: float = -5.0 / 7.0,
    ) -> None:
        self.alpha, self.beta, self.m0, self.m1 = alpha, beta, m0, m1

    def params(self):
        return {"alpha": self.alpha, "beta": self.beta, "m0": self.m0, "m1": self.m1}

    def diode(self, x):
        """``phi(x)``, the piecewise-linear diode current, for arrays or tensors."""
        return self.m1 * x + 0.5 * (self.m0 - self.m1) * (abs(x + 1.0) - abs(x - 1.0))

    def f(self, x):
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        return stack([self.alpha * (x2 - x1 - self.diode(x1)), x1 - x2 + x3, -self.beta * x2])

    def f_jacobian(self, x):
        slope = np.where(np.abs(x[..., 0]) < 1.0, self.m0, self.m1)
        jacobian = np.zeros((*x.shape, 3))
        jacobian[..., 0, 0] = -self.alpha * (1.0 + slope)
        jacobian[..., 0, 1] = self.alpha
        jacobian[..., 1, 0] = 1.0
        jacobian[..., 1, 1] = -1.0
        jacobian[..., 1, 2] = 1.0
        jacobian[..., 2, 1] = -self.beta
        return jacobian

    def compiled(self):
        return measured_states(
            [self.measured], self.g, [self.alpha, self.beta, self.m0, self.m1],
            _drift, _drift_jacobian, drift_flops=14, jacobian_flops=3, jacobian_nonzeros=6,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    alpha, beta, m0, m1 = p[0], p[1], p[2], p[3]
    for j in range(x.shape[1]):
        x1, x2, x3 = x[0, j], x[1, j], x[2, j]
        diode = m1 * x1 + 0.5 * (m0 - m1) * (abs(x1 + 1.0) - abs(x1 - 1.0))
        out[0, j] = alpha * (x2 - x1 - diode)
        out[1, j] = x1 - x2 + x3
        out[2, j] = -beta * x2


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    alpha, beta, m0, m1 = p[0], p[1], p[2], p[3]
    out[:, :, :] = 0.0
    for j in range(x.shape[1]):
        slope = m0 if abs(x[0, j]) < 1.0 else m1
        out[0, 0, j] = -alpha * (1.0 + slope)
        out[0, 1, j] = alpha
        out[1, 0, j] = 1.0
        out[1, 1, j] = -1.0
        out[1, 2, j] = 1.0
        out[2, 1, j] = -beta
