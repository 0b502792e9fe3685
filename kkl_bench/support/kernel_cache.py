"""Filter kernels bound to one model's functions, compiled once per machine.

The compiled engines' kernels (the EKF's, the UKF's, the EnKF's, the particle filter's
propagation) take the model's numba functions as their first arguments
(:class:`kkl_bench.protocol.compiled.CompiledModel`), so numba compiles one
specialization per system and sensor, and it cannot cache a function of functions on
disk: every process paid the compilation again (20-80 s a specialization, most of
``kkl-bench check ekf``). :func:`bind` writes a small module whose one function calls
the kernel with the functions named as globals, and compiles it with numba's on-disk
cache (:func:`kkl_bench.support.cache.import_generated`, the cache's ``bound_kernels/``): the
next process loads the machine code instead. The kernel is the same, so are its
estimates. :func:`bind_once` compiles a kernel once for every model instead, the
functions passed as first-class function values: the particle filter's, whose every call
of a model function sweeps its thousands of particles.

numba's cache of a function checks the function's own file, not the code it calls, so
the module's source carries a digest of this package's code, of the packages that define
the bound functions (a plugin's system, every Python file of its top-level package: the
helpers its functions call included) and of numba's version: a change to any is a new
module, compiled afresh.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import inspect
from collections.abc import Callable
from pathlib import Path

import numba

from kkl_bench.protocol.compiled import FUNCTION_TYPES
from kkl_bench.support.cache import code_digest, default_cache_dir, import_generated

FOLDER = "bound_kernels"
"""The cache's folder of bound kernels (:func:`bind`)."""


def _global_name(function) -> str | None:
    """``module.qualname`` by which ``function`` (a numba dispatcher) can be imported, or
    None where it cannot (a closure, a function of ``__main__``)."""
    python = getattr(function, "py_func", None)
    if python is None or "<" in python.__qualname__ or python.__module__ == "__main__":
        return None
    module = importlib.import_module(python.__module__)
    if getattr(module, python.__qualname__, None) is not function:
        return None
    return f"{python.__module__}.{python.__qualname__}"


def bind(kernel, *functions) -> Callable:
    """``kernel`` (a numba dispatcher) with ``functions`` (numba dispatchers) as its first
    arguments, compiled with numba's on-disk cache: call it with the kernel's other
    arguments. Where a function or the kernel cannot be imported by name (a plugin's
    closure), the kernel with the functions bound in Python, compiled as before."""
    return _bound(kernel, functions)


def defining_code_digest(names: list[str]) -> str:
    """A digest of the code behind the functions named ``module.qualname``, outside this
    package (which :func:`~kkl_bench.support.cache.code_digest` covers): every Python file of each
    one's top-level package, or its module's file where it is a lone module."""
    digest = hashlib.sha256()
    for package in sorted({name.partition(".")[0] for name in names} - {"kkl_bench"}):
        module = importlib.import_module(package)
        roots = [Path(path) for path in getattr(module, "__path__", [])]
        files = {(root, path) for root in roots for path in root.rglob("*.py")}
        if not roots:
            path = Path(inspect.getfile(module))
            files = {(path.parent, path)}
        for root, path in sorted(files):
            digest.update(f"{package}/{path.relative_to(root).as_posix()}".encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def bind_once(kernel, *functions) -> Callable:
    """``kernel`` (a numba dispatcher) with ``functions`` (a compiled model's numba
    dispatchers, named by the kernel's first parameters as in
    :data:`~kkl_bench.protocol.compiled.FUNCTION_TYPES`) as its first arguments, compiled
    once for every model: the functions are passed as first-class function values,
    called through their address, so the kernel's machine code does not depend on them.
    It is compiled with numba's on-disk cache, as :func:`bind`'s kernels are, and a new
    system or sensor costs only the compilation of its own functions. Call it with the
    kernel's other arguments.

    The price is an indirect call for each call of a model function, which numba cannot
    inline into the kernel: small beside a call that sweeps thousands of points (the
    particle filter's), not beside a step of a few hundred operations (the EKF's, the
    UKF's, the EnKF's: :func:`bind`; protocol 6.3 gives the measurements)."""
    parameters = list(inspect.signature(kernel.py_func).parameters)[: len(functions)]
    unknown = [name for name in parameters if name not in FUNCTION_TYPES]
    if unknown:
        raise ValueError(
            f"bind_once: {kernel.py_func.__qualname__}'s parameters {unknown} are not a "
            f"compiled model's functions; valid: {', '.join(FUNCTION_TYPES)}"
        )
    function_types = tuple(FUNCTION_TYPES[name] for name in parameters)
    shared = _shared(kernel)

    def call(*rest):
        argument_types = (*function_types, *(numba.typeof(value) for value in rest))
        return _entry_point(shared, argument_types)(*functions, *rest)

    return call


@functools.cache
def _bound(kernel, functions: tuple) -> Callable:
    names = [_global_name(function) for function in (kernel, *functions)]
    if None in names:
        return functools.partial(kernel, *functions)
    rest = list(inspect.signature(kernel.py_func).parameters)[len(functions) :]
    return _generated(kernel, names, rest).kernel


@functools.cache
def _shared(kernel):
    name = _global_name(kernel)
    if name is None:
        raise ValueError(
            f"bind_once: the kernel {kernel.py_func.__qualname__} cannot be imported by "
            "name; define it at the top level of a module"
        )
    return _generated(kernel, [name], list(inspect.signature(kernel.py_func).parameters)).kernel


@functools.cache
def _entry_point(shared, argument_types: tuple) -> Callable:
    """The machine code of ``shared`` for ``argument_types`` (loaded from numba's cache
    where it is there), called without the dispatcher's search for a match."""
    return shared.compile(argument_types)


def _generated(kernel, names: list[str], parameters: list[str]):
    """A generated module whose ``kernel(*parameters)`` calls ``names[0]`` (``kernel``) with
    the functions ``names[1:]`` and ``parameters``, compiled with numba's on-disk cache and
    the kernel's own options."""
    modules = sorted({name.rpartition(".")[0] for name in names})
    options = "".join(  # the kernel's own, e.g. error_model="numpy"
        f", {key}={value!r}"
        for key, value in sorted(kernel.targetoptions.items())
        if key in ("error_model", "fastmath")
    )
    code = f"{code_digest()}-{defining_code_digest(names)}-numba{numba.__version__}"
    purpose = "bound to its model" if len(names) > 1 else "for every model"
    source = "\n".join(
        [
            f'"""{names[0]} {purpose} (kkl_bench.support.kernel_cache; code {code})."""',
            "",
            "import numba",
            "",
            *(f"import {module}" for module in modules),
            "",
            "",
            f"@numba.njit(cache=True{options})",
            f"def kernel({', '.join(parameters)}):",
            f"    return {names[0]}({', '.join([*names[1:], *parameters])})",
            "",
        ]
    )
    return import_generated(source, default_cache_dir() / FOLDER, kernel.py_func.__name__)
