"""The protocol's model in a form numba compiles: what the compiled filter engines run.

A built-in system offers :meth:`~kkl_bench.protocol.system.System.compiled`: a
:class:`CompiledModel` whose functions sweep over points: they evaluate every column of
``x: (n_x, m)`` (a batch of trajectories, of ensemble members, ...) into a preallocated
output whose last axis is the same ``m`` points, with the system's parameters passed as
a float64 array. The points are the last axis so that each operation runs along
contiguous memory, as the vector units want. A filter kernel receives the functions as
arguments, so numba compiles one specialization per system (and sensor) and calls them
without Python in the loop.
:func:`rk4_step` and :func:`rk4_step_jacobian` are the protocol's RK4 step
(:mod:`kkl_bench.protocol.simulate`) on these functions, with the same operations in
the same order: ``tests/test_compiled_model.py`` checks every built-in system's
compiled model and step against the numpy ones.

A system without a compiled form (a plugin's) returns None, and the filters fall back
to their reference engine.

Shapes: ``x: (n_x, m)``, ``p``: the system's parameters, ``q``: the output's (the
measured state indices, as float64), ``s``: the sensor's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

_VECTOR, _SWEEP, _JACOBIANS = (  # C-contiguous float64: (k,), (n, m), (n_y, n_x, m)
    numba.types.float64[::1],
    numba.types.float64[:, ::1],
    numba.types.float64[:, :, ::1],
)


def _returning_nothing(*arguments) -> numba.types.FunctionType:
    return numba.types.FunctionType(numba.types.void(*arguments))


FUNCTION_TYPES = {
    "drift": _returning_nothing(_SWEEP, _VECTOR, _SWEEP),
    "drift_jacobian": _returning_nothing(_SWEEP, _VECTOR, _JACOBIANS),
    "output": _returning_nothing(_SWEEP, _VECTOR, _SWEEP),
    "output_jacobian": _returning_nothing(_SWEEP, _VECTOR, _JACOBIANS),
    "sense": _returning_nothing(_SWEEP, _VECTOR),
    "sense_slope": _returning_nothing(_SWEEP, _VECTOR, _SWEEP),
    "constrain": _returning_nothing(_SWEEP, _VECTOR),
}
"""numba's first-class type of each :class:`CompiledModel` function, by its name: its
arrays C-contiguous float64 (the sweeps, the Jacobians, the parameters), nothing
returned. A kernel that takes the functions as values of these types
(:func:`kkl_bench.support.kernel_cache.bind_once`) is compiled once for every model."""


@dataclass(frozen=True)
class CompiledModel:
    """One system's model, read through a sensor, as numba functions.

    Each function writes its result into its last argument (or in place), takes and
    writes C-contiguous float64 arrays and returns nothing: the types of
    :data:`FUNCTION_TYPES`, as which the particle filter's kernel receives them.

    Attributes
    ----------
    drift: ``drift(x, p, out)``: ``out (n_x, m) = f(x)`` at each of the ``m`` points of
        ``x (n_x, m)``.
    drift_jacobian: ``drift_jacobian(x, p, out)``: ``out (n_x, n_x, m) = df/dx`` (written
        whole).
    output: ``output(x, q, out)``: ``out (n_y, m) = h(x)``, the system's own output.
    output_jacobian: ``output_jacobian(x, q, out)``: ``out (n_y, n_x, m) = dh/dx`` (written
        whole).
    sense: ``sense(h, s)``: the sensor applied in place to ``h (n_y, m)``.
    sense_slope: ``sense_slope(h, s, out)``: ``out (n_y, m)``, the sensor's slope at ``h``
        (what a linearizing filter uses, :meth:`kkl_bench.measurement.Sensor.slope`).
    constrain: ``constrain(x, p)``: the system's constraint applied in place to ``x (n_x,
        m)`` (erratum E1).
    p, q, s: the parameters of the drift, the output and the sensor (float64 arrays).
    g: ``(n_x,)`` the input direction.
    n_y: number of outputs.
    drift_flops, jacobian_flops: floating-point operations of one ``drift`` and one
        ``drift_jacobian`` call (counted from the expressions; what cost floors use).
    jacobian_nonzeros: entries of ``df/dx`` that can be nonzero (``n_x^2`` when dense).
    constant_output_jacobian: whether the Jacobian of ``s(h(x))`` is the same at every
        point (a linear output through a sensor of constant slope): the particle filter
        then evaluates it once.
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
    constant_output_jacobian: bool = False

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
        constant_output_jacobian=True,
        **counts,
    )


@numba.njit(cache=True)
def select_states(x, q, out):
    for i in range(out.shape[0]):
        state = int(q[i])
        for j in range(x.shape[1]):
            out[i, j] = x[state, j]


@numba.njit(cache=True)
def select_states_jacobian(x, q, out):
    out[:, :, :] = 0.0
    for i in range(out.shape[0]):
        out[i, int(q[i]), :] = 1.0


@numba.njit(cache=True)
def no_sensor(h, s):
    pass


@numba.njit(cache=True)
def unit_slope(h, s, out):
    out[:, :] = 1.0


@numba.njit(cache=True)
def no_constraint(x, p):
    pass


@numba.njit(cache=True)
def matrix_column(x):
    """The one matrix ``x: (n_y, n)`` as the sweep ``(n_y, n, 1)`` (a view)."""
    return x.reshape((x.shape[0], x.shape[1], 1))


@numba.njit(inline="always")
def vector_field(drift, p, g, x, u, out):
    """``out = f(x) + g u`` (as :meth:`System.vector_field`); ``u: (m,)``, one input a point."""
    drift(x, p, out)
    for i in range(out.shape[0]):
        direction = g[i]
        for j in range(out.shape[1]):
            out[i, j] = out[i, j] + u[j] * direction


@numba.njit(inline="always")
def _stage_point(x, k, scale, out):
    """``out = x + scale k``, over every point."""
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            out[i, j] = x[i, j] + scale * k[i, j]


@numba.njit(inline="always")
def rk4_step(drift, p, g, x, u, dt, out, work):
    """``out`` = one RK4 step of ``f(x) + g u`` from every point of ``x``
    (:func:`simulate.rk4_step`).

    ``x, out: (n_x, m)``, ``u: (m,)``, ``work: (5, n_x, m)`` scratch (the stages ``k1..k4``
    and a stage point).
    """
    k1, k2, k3, k4, stage = work[0], work[1], work[2], work[3], work[4]
    half = 0.5 * dt
    vector_field(drift, p, g, x, u, k1)
    _stage_point(x, k1, half, stage)
    vector_field(drift, p, g, stage, u, k2)
    _stage_point(x, k2, half, stage)
    vector_field(drift, p, g, stage, u, k3)
    _stage_point(x, k3, dt, stage)
    vector_field(drift, p, g, stage, u, k4)
    sixth = dt / 6.0
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            out[i, j] = x[i, j] + sixth * (k1[i, j] + 2.0 * k2[i, j] + 2.0 * k3[i, j] + k4[i, j])


@numba.njit(inline="always")
def _chain(stages, target, previous, scale):
    """``stages[target] = stages[4] @ (I + scale stages[previous])`` at every point: one
    stage of the chain rule, on slices of one ``(5, n, n, m)`` array (indexed whole: a view
    costs reference counting, more than a small product's arithmetic)."""
    n, points = stages.shape[1], stages.shape[3]
    for i in range(n):
        for j in range(n):
            for point in range(points):
                stages[target, i, j, point] = 0.0
            for k in range(n):
                if k == j:
                    for point in range(points):
                        factor = 1.0 + scale * stages[previous, k, j, point]
                        stages[target, i, j, point] += stages[4, i, k, point] * factor
                else:
                    for point in range(points):
                        factor = scale * stages[previous, k, j, point]
                        stages[target, i, j, point] += stages[4, i, k, point] * factor


@numba.njit(inline="always")
def rk4_step_jacobian(drift, drift_jacobian, p, g, x, u, dt, out, work, stages):
    """``out (n_x, n_x, m)`` = the Jacobian of :func:`rk4_step` at every point of ``x`` by
    the chain rule (:func:`simulate.rk4_step_jacobian`). ``work: (5, n_x, m)``, ``stages:
    (5, n_x, n_x, m)`` scratch (``dk1..dk4`` and the Jacobian at a stage point)."""
    k, stage = work[0], work[4]
    half = 0.5 * dt
    vector_field(drift, p, g, x, u, k)
    drift_jacobian(x, p, stages[0])
    _stage_point(x, k, half, stage)
    vector_field(drift, p, g, stage, u, k)
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 1, 0, half)
    _stage_point(x, k, half, stage)
    vector_field(drift, p, g, stage, u, k)
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 2, 1, half)
    _stage_point(x, k, dt, stage)
    drift_jacobian(stage, p, stages[4])
    _chain(stages, 3, 2, dt)
    sixth = dt / 6.0
    n, points = x.shape
    for i in range(n):
        for j in range(n):
            identity = 1.0 if i == j else 0.0
            for point in range(points):
                out[i, j, point] = identity + sixth * (
                    stages[0, i, j, point]
                    + 2.0 * stages[1, i, j, point]
                    + 2.0 * stages[2, i, j, point]
                    + stages[3, i, j, point]
                )


@numba.njit(inline="always")
def sensed_output(model_output, sense, q, s, x, out):
    """``out (n_y, m) = s(h(x))``: the system's output read through the sensor."""
    model_output(x, q, out)
    sense(out, s)
