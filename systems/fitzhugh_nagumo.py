"""FitzHugh-Nagumo neuron, driven by its injected current, on a five times faster clock.

``dv = c (v - v^3 / 3 - w + I0 + u)``, ``dw = c (v + a - b w) / tau``, ``y = v``
(the membrane voltage). The parameters are FitzHugh's (1961) in the form
popularized by Izhikevich and FitzHugh (Scholarpedia, 2006): ``a = 0.7``,
``b = 0.8``, ``tau = 12.5``, with a bias current ``I0 = 0.5`` on which the input
``u`` adds. With ``I0 = 0.5`` and no input the neuron spikes on a limit cycle of
period about 39.5 model time units; without the bias it rests at
``(v, w) = (-1.199, -0.624)``, which would make the ``zero`` regime trivial.
One protocol second is ``c = 5`` model time units (a choice of unit, not of
dynamics), so a 50 s horizon holds about six spikes instead of 1.3.
"""

import numba
import numpy as np

from kkl_bench.protocol.compiled import measured_states
from kkl_bench.protocol.system import MeasureOneState, stack
from kkl_bench.registry import systems


@systems.register("fitzhugh_nagumo")
class FitzHughNagumo(MeasureOneState):
    name = "fitzhugh_nagumo"
    state_names = ("v", "w")
    time_scale = 5.0
    g = np.array([time_scale, 0.0])
    # covers the unforced limit cycle (v in [-1.97, 1.85], w in [-0.25, 1.39])
    x0_low = np.array([-2.0, -0.5])
    x0_high = np.array([2.0, 1.5])
    measured = 0

    def __init__(
        self, a: float = 0.7, b: float = 0.8, tau: float = 12.5, bias_current: float = 0.5
    ) -> None:
        self.a, self.b, self.tau, self.bias_current = a, b, tau, bias_current

    def params(self):
        return {"a": self.a, "b": self.b, "tau": self.tau, "I0": self.bias_current}

    def f(self, x):
        v, w = x[..., 0], x[..., 1]
        c = self.time_scale
        return stack(
            [
                c * (v - v * v * v / 3.0 - w + self.bias_current),
                c * (v + self.a - self.b * w) / self.tau,
            ]
        )

    def f_jacobian(self, x):
        v = x[..., 0]
        c = self.time_scale
        jacobian = np.zeros((*x.shape, 2))
        jacobian[..., 0, 0] = c * (1.0 - v * v)
        jacobian[..., 0, 1] = -c
        jacobian[..., 1, 0] = c / self.tau
        jacobian[..., 1, 1] = -c * self.b / self.tau
        return jacobian

    def compiled(self):
        p = [self.a, self.b, self.tau, self.bias_current, self.time_scale]
        return measured_states(
            [self.measured], self.g, p, _drift, _drift_jacobian,
            drift_flops=12, jacobian_flops=6, jacobian_nonzeros=4,
        )  # fmt: skip


@numba.njit(cache=True)
def _drift(x, p, out):
    a, b, tau, bias_current, c = p[0], p[1], p[2], p[3], p[4]
    for j in range(x.shape[1]):
        v, w = x[0, j], x[1, j]
        out[0, j] = c * (v - v * v * v / 3.0 - w + bias_current)
        out[1, j] = c * (v + a - b * w) / tau


@numba.njit(cache=True)
def _drift_jacobian(x, p, out):
    b, tau, c = p[1], p[2], p[4]
    for j in range(x.shape[1]):
        v = x[0, j]
        out[0, 0, j] = c * (1.0 - v * v)
        out[0, 1, j] = -c
        out[1, 0, j] = c / tau
        out[1, 1, j] = -c * b / tau
