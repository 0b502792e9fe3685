"""Straight-line scalar source traced from the compiled model: what the unrolled kernels run.

The compiled engines' generic kernels (``estimators/filters/kalman_kernels.py``, over the model
of :mod:`kkl_bench.protocol.compiled`) sweep each operation over the batch, with the
sizes known only at run time: a loop per operation and a call per model function,
whatever the batch. An unrolled kernel (``estimators/filters/kalman_unrolled.py``) instead runs
one trajectory's whole step as straight-line scalar code. Its source is written by
tracing: an algorithm written over :class:`Scalar` values, and the
model's own numba functions run in Python (``py_func``) on object arrays of them, record
each operation as one line of a :class:`Program`, in the order they run, so the unrolled
kernel performs the generic kernel's operations in the generic kernel's order and its
estimates are bit-identical (``tests/test_unrolled_kernels.py``).

A :class:`Scalar` records an operation even where an operand is a constant (``0.0 + v``,
``v * 0.0``): folding it would change what a NaN or an infinity propagates, and the
generic kernel computes it too.
"""

from __future__ import annotations

import math

import numpy as np


class UntraceableError(TypeError):
    """A function cannot be traced into straight-line code: it branches on a traced value
    (``m0 if abs(x) < 1.0 else m1``) or needs its number."""


def literal(value: float) -> str:
    """``value`` as Python source (``math.inf``, ``-math.inf`` and ``math.nan`` included)."""
    value = float(value)
    if math.isnan(value):
        return "math.nan"
    if math.isinf(value):
        return "math.inf" if value > 0 else "-math.inf"
    return repr(value)


def source_of(value) -> str:
    """The source of a :class:`Scalar`, of a Python number, or ``value`` itself if it is
    source already (a string)."""
    if isinstance(value, str):
        return value
    return value.name if isinstance(value, Scalar) else literal(value)


class Program:
    """Lines of straight-line code, each binding one new local (``v0``, ``v1``, ...)."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def let(self, expression: str) -> Scalar:
        """Bind ``expression`` to a new local; returns it."""
        name = f"v{len(self.lines)}"
        self.lines.append(f"{name} = {expression}")
        return Scalar(self, name)

    def named(self, name: str) -> Scalar:
        """A :class:`Scalar` for a local bound elsewhere (a kernel argument read before the
        loop, a state loaded at its top)."""
        return Scalar(self, name)

    def call(self, function: str, *arguments) -> Scalar:
        """``function(arguments...)`` bound to a new local."""
        return self.let(f"{function}({', '.join(source_of(a) for a in arguments)})")

    def select(self, condition, if_true, if_false) -> Scalar:
        """``if_true if condition else if_false`` (``condition``: source or a Scalar), as a
        call of the generated module's :data:`CHOOSE` (a branch per choice would multiply
        the blocks numba's front end analyses; the compiler inlines the call)."""
        return self.let(
            f"choose({source_of(condition)}, {source_of(if_true)}, {source_of(if_false)})"
        )


def _operator(symbol: str, reflected: bool = False):
    """A :class:`Scalar` method recording ``self symbol other`` (``other symbol self`` if
    ``reflected``)."""

    def method(self, other):
        return self._binary(symbol, *((other, self) if reflected else (self, other)))

    return method


class Scalar:
    """A float64 local of a :class:`Program`; arithmetic on it appends a line.

    Supports ``+ - * /``, unary ``-``, ``abs`` and numpy's one-argument functions
    (``np.tanh``, ``np.rint``, ...), which a model's numba function may use; ``float()``
    raises: a traced value has no value yet.
    """

    __slots__ = ("name", "program")

    def __init__(self, program: Program, name: str) -> None:
        self.program, self.name = program, name

    def __repr__(self) -> str:
        return f"Scalar({self.name})"

    def _binary(self, operator: str, left, right) -> Scalar:
        return self.program.let(f"{source_of(left)} {operator} {source_of(right)}")

    __add__ = _operator("+")
    __radd__ = _operator("+", reflected=True)
    __sub__ = _operator("-")
    __rsub__ = _operator("-", reflected=True)
    __mul__ = _operator("*")
    __rmul__ = _operator("*", reflected=True)
    __truediv__ = _operator("/")
    __rtruediv__ = _operator("/", reflected=True)

    def __pow__(self, exponent):
        power = repr(exponent) if isinstance(exponent, int) else source_of(exponent)
        return self.program.let(f"{self.name} ** {power}")

    def __neg__(self):
        return self.program.let(f"-{self.name}")

    def __abs__(self):
        return self.program.call("abs", self)

    def __float__(self):
        raise UntraceableError(f"{self.name} is traced: it has no value at tracing time")

    def __bool__(self):
        raise UntraceableError(f"{self.name} is traced: a branch on it cannot be unrolled")

    def _compare(self, other):
        raise UntraceableError(f"{self.name} is traced: a branch on it cannot be unrolled")

    __lt__ = __le__ = __gt__ = __ge__ = _compare

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        """numpy's functions on a traced value (``np.tanh(v)``, ``np.float64(2) * v``):
        the same function in the source."""
        if method != "__call__" or kwargs:
            return NotImplemented
        operands = [float(a) if isinstance(a, np.generic) else a for a in inputs]
        if ufunc.__name__ in _OPERATORS:
            return self._binary(_OPERATORS[ufunc.__name__], *operands)
        if ufunc.__name__ == "negative":
            return -self
        if ufunc.__name__ == "absolute":
            return abs(self)
        if ufunc.nin == 1:
            return self.program.call(f"np.{ufunc.__name__}", self)
        return NotImplemented


_OPERATORS = {"add": "+", "subtract": "-", "multiply": "*", "divide": "/", "true_divide": "/"}


CHOOSE = """@numba.njit(cache=True)
def choose(condition, if_true, if_false):
    return if_true if condition else if_false
"""
"""The source of ``choose``, which a generated module using :meth:`Program.select`
defines."""


def scalars(program: Program, prefix: str, shape: tuple[int, ...]) -> np.ndarray:
    """An object array of ``shape`` whose entries are the locals ``{prefix}_{i}_{j}...``."""
    out = np.empty(shape, dtype=object)
    for index in np.ndindex(*shape):
        out[index] = program.named("_".join([prefix, *map(str, index)]))
    return out


def loaded(array: str, prefix: str, shape: tuple[int, ...], lane: str = "") -> list[str]:
    """Lines binding ``{prefix}_{i}_{j}... = {array}[i, j, ..., lane]`` for every index of
    ``shape`` (``lane``: a trailing index, or none)."""
    lines = []
    for index in np.ndindex(*shape):
        subscript = ", ".join([*map(str, index), *([lane] if lane else [])])
        lines.append(f"{'_'.join([prefix, *map(str, index)])} = {array}[{subscript}]")
    return lines


def points(values: np.ndarray) -> np.ndarray:
    """``values: (n,)`` as the sweep of one point ``(n, 1)`` a model function takes."""
    return values.reshape(*values.shape, 1)


def model_call(function, *arguments) -> None:
    """Run a model's numba ``function`` in Python on object arrays (tracing it)."""
    getattr(function, "py_func", function)(*arguments)
