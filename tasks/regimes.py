"""The protocol's four input regimes (protocol section 3)."""

import numpy as np

from kkl_bench.protocol.signals import Regime
from kkl_bench.registry import regimes


@regimes.register("zero")
class Zero(Regime):
    """``u(t) = 0``."""

    name = "zero"

    def params_from_uniform(self, r):
        return np.empty((len(r), 0))

    def signal(self, t, params):
        return np.zeros((len(params), len(t)))


@regimes.register("constant")
class Constant(Regime):
    """``u(t) = c`` with ``c ~ U[-1, 1]``."""

    name = "constant"
    param_names = ("c",)

    def params_from_uniform(self, r):
        return -1.0 + 2.0 * r[:, :1]

    def signal(self, t, params):
        return np.broadcast_to(params[:, :1], (len(params), len(t))).copy()


@regimes.register("sinusoid")
class Sinusoid(Regime):
    """``u(t) = A sin(w t + phi)``, ``A ~ U[0.5, 1]``, ``w ~ U[0.5, 2]`` rad/s, ``phi ~ U[0, 2 pi)``."""

    name = "sinusoid"
    param_names = ("A", "w", "phi")

    def params_from_uniform(self, r):
        return np.stack([0.5 + 0.5 * r[:, 0], 0.5 + 1.5 * r[:, 1], 2.0 * np.pi * r[:, 2]], axis=1)

    def signal(self, t, params):
        amplitude, omega, phase = (params[:, i : i + 1] for i in range(3))
        return amplitude * np.sin(omega * t + phase)


@regimes.register("square")
class Square(Regime):
    """``u(t) = A sign(sin(2 pi t / P + phi))``, ``A ~ U[0.5, 1]``, ``P ~ U[2, 10]`` s, ``phi ~ U[0, 2 pi)``."""

    name = "square"
    param_names = ("A", "P", "phi")

    def params_from_uniform(self, r):
        return np.stack([0.5 + 0.5 * r[:, 0], 2.0 + 8.0 * r[:, 1], 2.0 * np.pi * r[:, 2]], axis=1)

    def signal(self, t, params):
        amplitude, period, phase = (params[:, i : i + 1] for i in range(3))
        return amplitude * np.sign(np.sin(2.0 * np.pi * t / period + phase))
