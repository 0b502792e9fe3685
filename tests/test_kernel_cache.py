"""Filter kernels bound to a model's functions are compiled once per machine, and a
kernel bound once is compiled once for every model (kkl_bench.support.kernel_cache): the
same results, and the next process loads them."""

import functools
import subprocess
import sys

import numba
import numpy as np
import pytest

from kkl_bench.protocol import compiled
from kkl_bench.registry import systems
from kkl_bench.support import kernel_cache

BOUND_STEP = """
import numpy as np
from kkl_bench.support.kernel_cache import bind
from kkl_bench.protocol import compiled
from kkl_bench.registry import systems

model = systems.get("duffing")().compiled()
step = bind(compiled.rk4_step, model.drift)
x = np.array([[0.5, -1.0], [0.25, 2.0]])
out, work = np.empty_like(x), np.empty((5, *x.shape))
step(model.p, model.g, x, np.array([0.1, -0.3]), 0.05, out, work)
print(sum(step.stats.cache_hits.values()), *out.ravel())
"""

STEP_BOUND_ONCE = """
import numpy as np
from kkl_bench.support import kernel_cache
from kkl_bench.protocol import compiled
from kkl_bench.registry import systems

model = systems.get("vdp")().compiled()
x = np.array([[0.5, -1.0], [0.25, 2.0]])
out, work = np.empty_like(x), np.empty((5, *x.shape))
kernel_cache.bind_once(compiled.rk4_step, model.drift)(model.p, model.g, x, np.array([0.1, -0.3]), 0.05, out, work)
print(sum(kernel_cache._shared(compiled.rk4_step).stats.cache_hits.values()), *out.ravel())
"""


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache for this test, and no kernel bound in this process yet."""
    monkeypatch.setenv("KKL_BENCH_CACHE", str(tmp_path))
    clear()
    yield tmp_path
    clear()


def clear():
    for memo in (kernel_cache._bound, kernel_cache._shared, kernel_cache._entry_point):
        memo.cache_clear()


def step_inputs():
    x = np.array([[0.5, -1.0], [0.25, 2.0]])  # (n_x, m): two points of Duffing's state
    return x, np.array([0.1, -0.3]), 0.05, np.empty_like(x), np.empty((5, *x.shape))


def test_a_bound_kernel_computes_what_the_kernel_does(cache):
    model = systems.get("duffing")().compiled()
    x, u, dt, bound_out, work = step_inputs()
    kernel_cache.bind(compiled.rk4_step, model.drift)(model.p, model.g, x, u, dt, bound_out, work)
    direct_out = np.empty_like(x)
    compiled.rk4_step(model.drift, model.p, model.g, x, u, dt, direct_out, work)
    np.testing.assert_array_equal(bound_out, direct_out)
    assert len(list((cache / kernel_cache.FOLDER).glob("rk4_step_*.py"))) == 1


@pytest.mark.parametrize("script", [BOUND_STEP, STEP_BOUND_ONCE], ids=["bind", "bind_once"])
def test_the_next_process_loads_the_kernel_from_the_cache(cache, script):
    runs = [
        subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, check=True
        ).stdout.split()
        for _ in range(2)
    ]
    assert runs[0][0] == "0" and int(runs[1][0]) >= 1  # compiled, then loaded
    assert runs[0][1:] == runs[1][1:]  # the same numbers


def test_a_function_that_cannot_be_imported_by_name_is_bound_in_python(cache):
    @numba.njit
    def drift(x, p, out):  # a closure: no module attribute names it
        out[:] = -x

    x, u, dt, out, work = step_inputs()
    step = kernel_cache.bind(compiled.rk4_step, drift)
    assert isinstance(step, functools.partial)
    step(np.zeros(0), np.zeros(2), x, u, dt, out, work)
    expected = np.empty_like(x)
    compiled.rk4_step(drift, np.zeros(0), np.zeros(2), x, u, dt, expected, work)
    np.testing.assert_array_equal(out, expected)
    assert not (cache / kernel_cache.FOLDER).exists()


def test_a_change_anywhere_in_a_plugins_package_is_new_code(tmp_path, monkeypatch):
    """numba's cache checks only the file of a function, not the helpers it calls: the
    bound kernel's digest covers the whole package that defines the function."""
    package = tmp_path / "site" / "my_plugin"
    (package / "models").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "models" / "__init__.py").write_text("")
    (package / "models" / "drift.py").write_text("from my_plugin.helpers import gain\n")
    (package / "helpers.py").write_text("gain = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    names = ["kkl_bench.protocol.compiled.rk4_step", "my_plugin.models.drift.drift"]
    before = kernel_cache.defining_code_digest(names)
    assert kernel_cache.defining_code_digest(names) == before
    assert kernel_cache.defining_code_digest(names[:1]) != before  # the package alone
    (package / "helpers.py").write_text("gain = 2.0\n")  # a helper, not the function's file
    assert kernel_cache.defining_code_digest(names) != before


def test_a_kernel_bound_once_computes_what_the_kernel_does_for_every_model(cache):
    x, u, dt, out, work = step_inputs()
    for name in ("duffing", "vdp"):
        model = systems.get(name)().compiled()
        kernel_cache.bind_once(compiled.rk4_step, model.drift)(
            model.p, model.g, x, u, dt, out, work
        )
        expected = np.empty_like(x)
        compiled.rk4_step(model.drift, model.p, model.g, x, u, dt, expected, work)
        np.testing.assert_array_equal(out, expected)
    assert len(kernel_cache._shared(compiled.rk4_step).signatures) == 1  # one compilation
    assert len(list((cache / kernel_cache.FOLDER).glob("rk4_step_*.py"))) == 1


def test_a_closure_is_a_function_value_like_any_other(cache):
    @numba.njit
    def drift(x, p, out):  # a plugin's closure: bind cannot name it, bind_once need not
        out[:] = -x

    x, u, dt, out, work = step_inputs()
    kernel_cache.bind_once(compiled.rk4_step, drift)(np.zeros(0), np.zeros(2), x, u, dt, out, work)
    expected = np.empty_like(x)
    compiled.rk4_step(drift, np.zeros(0), np.zeros(2), x, u, dt, expected, work)
    np.testing.assert_array_equal(out, expected)


def test_a_kernel_that_cannot_be_imported_by_name_is_refused(cache):
    @numba.njit
    def kernel(drift, x, out):
        drift(x, np.zeros(0), out)

    with pytest.raises(ValueError, match=r"kernel .*cannot be imported by name"):
        kernel_cache.bind_once(kernel, compiled.no_constraint)


def test_a_kernel_parameter_that_is_no_model_function_is_named(cache):
    with pytest.raises(
        ValueError, match=r"\['x'\] are not a compiled model's functions; valid: drift"
    ):
        kernel_cache.bind_once(compiled.matrix_column, compiled.no_constraint)
