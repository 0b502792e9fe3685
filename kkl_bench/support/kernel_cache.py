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
estimates.

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


@functools.cache
def _bound(kernel, functions: tuple) -> Callable:
    names = [_global_name(function) for function in (kernel, *functions)]
    if None in names:
        return functools.partial(kernel, *functions)
    rest = list(inspect.signature(kernel.py_func).parameters)[len(functions) :]
    modules = sorted({name.rpartition(".")[0] for name in names})
    options = "".join(  # the kernel's own, e.g. error_model="numpy"
        f", {key}={value!r}"
        for key, value in sorted(kernel.targetoptions.items())
        if key in ("error_model", "fastmath")
    )
    code = f"{code_digest()}-{defining_code_digest(names)}-numba{numba.__version__}"
    source = "\n".join(
        [
            f'"""{names[0]} bound to its model (kkl_bench.support.kernel_cache; code {code})."""',
            "",
            "import numba",
            "",
            *(f"import {module}" for module in modules),
            "",
            "",
            f"@numba.njit(cache=True{options})",
            f"def kernel({', '.join(rest)}):",
            f"    return {names[0]}({', '.join([*names[1:], *rest])})",
            "",
        ]
    )
    folder = default_cache_dir() / FOLDER
    return import_generated(source, folder, kernel.py_func.__name__).kernel
