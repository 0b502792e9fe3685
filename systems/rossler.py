"""Rossler system: ``dx1 = -x2 - x3 + u``, ``dx2 = x1 + a x2``, ``dx3 = b + x3 (x1 - c)``, ``y = x2``."""

import numpy as np

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
