"""The protocol's model in a form numba compiles: what the compiled filter engines run.

A built-in system offers :meth:`~kkl_bench.protocol.system.System.compiled`: a
:class:`CompiledModel` whose functions evaluate one state vector (no batch axis)
into a preallocated output, with the system's parameters passed as a float64
array. A filter kernel receives the functions as arguments, so numba compiles one
specialization per system (and sensor) and calls them without Python in the loop.
:func:`rk4_step` and :func:`rk4_step_jacobian` are the protocol's RK4 step
(:mod:`kkl_bench.protocol.simulate`) on these functions, with the same operations in
the same order: ``tests/test_compiled_model.py`` checks every built-in system's
compiled model and step against the numpy ones.

A system without a compiled form (a plugin's) returns None, and the filters fall back
to their reference engine.

Shapes: ``x: (n_x,)``, ``p``: the system's parameters, ``q``: the output's (the measured
state indices, as float64), ``s``: the sensor's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np


@dataclass(frozen=True)
class CompiledModel:
    """One system's model, read through a sensor, as numba functions.

    Attributes
    ----------
    drift: ``drift(x, p, out)``: ``out (n_x,) = f(x)``.
    drift_jacobian: ``drift_jacobian(x, p, out)``: ``out (n_x, n_x) = df/dx`` (written whole).
    output: ``output(x, q, out)``: ``out (n_y,) = h(x)``, the system's own output.
    output_jacobian: ``output_jacobian(x, q, out)``: ``out (n_y, n_x) = dh/dx`` (written whole).
    sense: ``sense(h, s)``: the sensor applied in place to ``h (n_y,)``.
    sense_slope: ``sense_slope(h, s, out)``: ``out (n_y,)``, the sensor's slope at ``h``
        (what a linearizing filter uses, :meth:`kkl_bench.measurement.Sensor.slope`).
    constrain: ``constrain(x, p)``: the system's constraint applied in place (erratum E1).
    p, q, s: the parameters of the drift, the output and the sensor (float64 arrays).
    g: ``(n_x,)`` the input direction.
    n_y: number of outputs.
    drift_flops, jacobian_flops: floating-point operations of one ``drift`` and one
        ``drift_jacobian`` call (counted from the expressions; what cost floors use).
    jacobian_nonzeros: entries of ``df/dx`` that can be nonzero (``n_x^2`` when dense).
    """

    drift: Any
    drift_jacobian: Any
    output: Any
    output_jacobian: Any
    sense: Any
    sense_slope: Any
    constrain: Any
    p: np.ndarray
    q: np.ndarray
    s: np.ndarray
    g: np.ndarray
    n_y: int
    drift_flops: int
    jacobian_flops: int
    jacobian_nonzeros: int

    @property
    def n_x(self) -> int:
        return self.g.shape[0]

    @property
    def step_flops(self) -> int:
        """Flops of one :func:`rk4_step`: four drifts plus ``g u`` (2 n each), three stage
        points (2 n each) and the weighted sum (7 n)."""
        n = self.n_x
        return 4 * (self.drift_flops + 2 * n) + 6 * n + 7 * n

    @property
    def step_jacobian_flops(self) -> int:
        """Flops of one :func:`rk4_step_jacobian` with dense products: three drifts and
        stage points, four Jacobians, three chain-rule products ``J (I + c dk)``
        (``2 n^3 + n^2 + n`` each) and the weighted sum (7 n^2)."""
        n = self.n_x
        stages = 3 * (self.drift_flops + 4 * n) + 4 * self.jacobian_flops
        return stages + 3 * (2 * n**3 + n**2 + n) + 7 * n**2

    @property
    def functions(self) -> tuple:
        """The functions in the order the kernels take them."""
        return (
            self.drift,
            self.drift_jacobian,
            self.output,
            self.output_jacobian,
            self.sense,
            self.sense_slope,
            self.constrain,
        )


def measured_states(
    indices, g: np.ndarray, p, drift, drift_jacobian, constrain=None, **counts
) -> CompiledModel:
    """A :class:`CompiledModel` whose output is the states ``indices``, with no sensor and
    (unless ``constrain`` is given) no constraint. ``counts``: the flop and nonzero counts."""
    q = np.asarray(indices, dtype=np.float64).reshape(-1)
    return CompiledModel(
        drift=drift,
        drift_jacobian=drift_jacobian,
        output=select_states,
        output_jacobian=select_states_jacobian,
        sense=no_sensor,
        sense_slope=unit_slope,
        constrain=no_constraint if constrain is None else constrain,
        p=np.ascontiguousarray(p, dtype=np.float64),
        q=q,
        s=np.zeros(0),
        g=np.ascontiguousarray(g, dtype=np.float64),
        n_y=q.shape[0],
        **counts,
    )


@numba.njit(cache=True)
def select_states(x, q, out):
    for j in range(out.shape[0]):
        out[j] = x[int(q[j])]


@numba.njit(cache=True)
def select_states_jacobian(x, q, out):
    out[:, :] = 0.0
    for j in range(out.shape[0]):
        out[j, int(q[j])] = 1.0


@numba.njit(cache=True)
def no_sensor(h, s):
    pass


@numba.njit(cache=True)
def unit_slope(h, s, out):
    out[:] = 1.0


@numba.njit(cache=True)
def no_constraint(x, p):
    pass


@numba.njit  # not cached: numba cannot cache a function of functions
def vector_field(drift, p, g, x, u, out):
    """``out = f(x) + g u`` (as :meth:`System.vector_field`)."""
    drift(x, p, out)
    for i in range(out.shape[0]):
        out[i] = out[i] + u * g[i]


@numba.njit  # not cached: numba cannot cache a function of functions
def rk4_step(drift, p, g, x, u, dt, out, work):
    """``out`` = one RK4 step of ``f(x) + g u`` from ``x`` (:func:`simulate.rk4_step`).

    ``work: (5, n_x)`` scratch (the stages ``k1..k4`` and a stage point).
    """
    n = x.shape[0]
    k1, k2, k3, k4, stage = work[0], work[1], work[2], work[3], work[4]
    half = 0.5 * dt
    vector_field(drift, p, g, x, u, k1)
    for i in range(n):
        stage[i] = x[i] + half * k1[i]
    vector_field(drift, p, g, stage, u, k2)
    for i in range(n):
        stage[i] = x[i] + half * k2[i]
    vector_field(drift, p, g, stage, u, k3)
    for i in range(n):
        stage[i] = x[i] + dt * k3[i]
    vector_field(drift, p, g, stage, u, k4)
    sixth = dt / 6.0
    for i in range(n):
        out[i] = x[i] + sixth * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@numba.njit(cache=True)
def _chain(stages, target, previous, scale):
    """``stages[target] = stages[4] @ (I + scale stages[previous])``: one stage of the chain
    rule, on slices of one ``(5, n, n)`` array (indexing it whole keeps the loop free of
    array views)."""
    n = stages.shape[1]
    for i in range(n):
        for j in range(n):
            total = 0.0
            for m in range(n):
                factor = scale * stages[previous, m, j]
                if m == j:
                    factor = 1.0 + factor
                total += stages[4, i, m] * factor
            stages[target, i, j] = total


@numba.njit  # not cached: numba cannot cache a function of functions
def rk4_step_jacobian(drift, drift_jacobian, p, g, x, u, dt, out, work, stages):
    """``out (n_x, n_x)`` = the Jacobian of :func:`rk4_step` at ``x`` by the chain rule
    (:func:`simulate.rk4_step_jacobian`). ``work: (5, n_x)``, ``stages: (5, n_x, n_x)``
    scratch (``dk1..dk4`` and the Jacobian at a stage point)."""
    n = x.shape[0]
    k, stage = work[0], work[4]
    half = 0.5 * dt
    vector_field(drift, p, g, x, u, k)
    drift_jacobian(x, p, stages[0])
    for i in range(n):
        stage[i] = x[i] + half * k[i]
    vector_field(drift, p, g, stage, u, k)
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 1, 0, half)
    for i in range(n):
        stage[i] = x[i] + half * k[i]
    vector_field(drift, p, g, stage, u, k)
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 2, 1, half)
    for i in range(n):
        stage[i] = x[i] + dt * k[i]
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 3, 2, dt)
    sixth = dt / 6.0
    for i in range(n):
        for j in range(n):
            identity = 1.0 if i == j else 0.0
            out[i, j] = identity + sixth * (
                stages[0, i, j] + 2.0 * stages[1, i, j] + 2.0 * stages[2, i, j] + stages[3, i, j]
            )


@numba.njit  # not cached: numba cannot cache a function of functions
def sensed_output(model_output, sense, q, s, x, out):
    """``out = s(h(x))``: the system's output read through the sensor."""
    model_output(x, q, out)
    sense(out, s)
