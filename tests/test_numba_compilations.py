"""The ``--numba-compilations`` report (tests/numba_compilations.py) on a run of its own."""

import json

import pytest

from tests.repository import REPOSITORY

COMPILING = """
import numba


@numba.njit
def double(x):
    return 2 * x


def test_compiles():
    assert double(2) == 4


def test_reuses_what_was_compiled():
    assert double(3) == 6
"""


@pytest.mark.parametrize("workers", [[], ["-n", "2"]], ids=["one process", "two workers"])
def test_each_test_lists_the_numba_compilations_it_started(pytester, monkeypatch, workers):
    monkeypatch.setenv("PYTHONPATH", str(REPOSITORY))
    pytester.makepyfile(test_compiling=COMPILING)
    stale = pytester.path / "out.jsonl.gw7"  # a worker of an earlier run: removed
    stale.write_text('{"test": "old", "compilations": [["old", 99.0]]}\n')
    result = pytester.runpytest_subprocess(
        "-p", "tests.numba_compilations", "--numba-compilations", "out.jsonl", *workers
    )
    result.assert_outcomes(passed=2)
    written = sorted(pytester.path.glob("out.jsonl*"))
    assert stale not in written and len(written) == (2 if workers else 1)
    records = {
        record["test"]: record["compilations"]
        for file in written
        for record in map(json.loads, file.read_text().splitlines())
    }
    assert set(records) == {
        "test_compiling.py::test_compiles",
        "test_compiling.py::test_reuses_what_was_compiled",
    }
    if not workers:  # in one process the second test finds the function compiled
        assert records["test_compiling.py::test_reuses_what_was_compiled"] == []
    ((function, seconds),) = records["test_compiling.py::test_compiles"]
    assert function == "test_compiling.double" and seconds > 0
    result.stdout.fnmatch_lines(["*numba compilations*", "*s  test_compiling.py::test_compiles"])
