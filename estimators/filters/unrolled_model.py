"""The model traced into straight-line code for the unrolled EKF and UKF: the system's drift
and Jacobian, and the RK4 step and its exact Jacobian, written out in scalars."""

from __future__ import annotations

import numpy as np

from kkl_bench.protocol.compiled import CompiledModel
from kkl_bench.protocol.scalar_source import (
    Program,
    model_call,
    points,
    scalars,
)


class Traced:
    """A model's functions traced at one trajectory: what the step's algorithm calls. The
    step's time quantities are the kernel's locals ``dt``, ``half`` (``dt / 2``), ``sixth``
    (``dt / 6``) and the previous sample's input ``u_k``."""

    def __init__(self, program: Program, model: CompiledModel) -> None:
        self.program, self.model = program, model
        self.n, self.n_y = model.n_x, model.n_y
        self.p = scalars(program, "p", model.p.shape)
        self.s = scalars(program, "s", model.s.shape)
        self.g = scalars(program, "g", model.g.shape)
        self.dt, self.half, self.sixth, self.u = map(program.named, ("dt", "half", "sixth", "u_k"))

    def drift(self, x: np.ndarray) -> np.ndarray:
        out = np.empty((self.n, 1), dtype=object)
        model_call(self.model.drift, points(x), self.p, out)
        return out[:, 0]

    def drift_jacobian(self, x: np.ndarray) -> np.ndarray:
        out = np.empty((self.n, self.n, 1), dtype=object)
        model_call(self.model.drift_jacobian, points(x), self.p, out)
        return out[:, :, 0]

    def vector_field(self, x: np.ndarray, u) -> np.ndarray:
        """``f(x) + g u`` (:func:`kkl_bench.protocol.compiled.vector_field`)."""
        out = self.drift(x)
        return np.array([out[i] + u * self.g[i] for i in range(self.n)], dtype=object)

    def constrain(self, x: np.ndarray) -> np.ndarray:
        out = points(x.copy())
        model_call(self.model.constrain, out, self.p)
        return out[:, 0]

    def output(self, x: np.ndarray) -> np.ndarray:
        out = np.empty((self.n_y, 1), dtype=object)
        model_call(self.model.output, points(x), self.model.q, out)
        return out

    def sensed_output(self, x: np.ndarray) -> np.ndarray:
        """``s(h(x)): (n_y,)`` (:func:`kkl_bench.protocol.compiled.sensed_output`)."""
        out = self.output(x)
        model_call(self.model.sense, out, self.s)
        return out[:, 0]

    def sensed_output_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``(n_y, n)``, as ``kalman_kernels._sensed_output_jacobian`` computes it."""
        h = self.output(x)
        slope = np.empty((self.n_y, 1), dtype=object)
        model_call(self.model.sense_slope, h, self.s, slope)
        out = np.empty((self.n_y, self.n, 1), dtype=object)
        model_call(self.model.output_jacobian, points(x), self.model.q, out)
        return np.array(
            [[slope[j, 0] * out[j, i, 0] for i in range(self.n)] for j in range(self.n_y)],
            dtype=object,
        )


def _stage_point(x, k, scale):
    return np.array([x[i] + scale * k[i] for i in range(len(x))], dtype=object)


def traced_rk4_step(model: Traced, x):
    """:func:`kkl_bench.protocol.compiled.rk4_step` at one trajectory."""
    u, dt, half, sixth = model.u, model.dt, model.half, model.sixth
    k1 = model.vector_field(x, u)
    k2 = model.vector_field(_stage_point(x, k1, half), u)
    k3 = model.vector_field(_stage_point(x, k2, half), u)
    k4 = model.vector_field(_stage_point(x, k3, dt), u)
    return np.array(
        [x[i] + sixth * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]) for i in range(len(x))],
        dtype=object,
    )


def _chain(stage_jacobian, previous, scale):
    """``stage_jacobian @ (I + scale previous)`` (``compiled._chain``)."""
    n = len(previous)
    out = np.empty((n, n), dtype=object)
    for i in range(n):
        for j in range(n):
            total = 0.0
            for k in range(n):
                factor = 1.0 + scale * previous[k, j] if k == j else scale * previous[k, j]
                total = total + stage_jacobian[i, k] * factor
            out[i, j] = total
    return out


def traced_rk4_step_jacobian(model: Traced, x):
    """:func:`kkl_bench.protocol.compiled.rk4_step_jacobian` at one trajectory."""
    u, dt, half, sixth = model.u, model.dt, model.half, model.sixth
    k = model.vector_field(x, u)
    d1 = model.drift_jacobian(x)
    stage = _stage_point(x, k, half)
    k = model.vector_field(stage, u)
    d2 = _chain(model.drift_jacobian(stage), d1, half)
    stage = _stage_point(x, k, half)
    k = model.vector_field(stage, u)
    d3 = _chain(model.drift_jacobian(stage), d2, half)
    stage = _stage_point(x, k, dt)
    d4 = _chain(model.drift_jacobian(stage), d3, dt)
    n = len(x)
    return np.array(
        [
            [
                (1.0 if i == j else 0.0)
                + sixth * (d1[i, j] + 2.0 * d2[i, j] + 2.0 * d3[i, j] + d4[i, j])
                for j in range(n)
            ]
            for i in range(n)
        ],
        dtype=object,
    )
