"""How long the command line takes to answer before it does any work: ``kkl-bench --help``,
a command's ``--help`` and an argument error, each a fresh process (what a user waits for).

Only the module of the command given is imported, and each handler imports what it runs
(:mod:`kkl_bench.cli`), so none of these loads torch, pandas or numba
(``tests/test_cli.py`` asserts which modules load; this measures the seconds). Run with
``python -m pytest tests/benchmarks/test_command_line.py --benchmark-only``.
"""

import subprocess
import sys

import pytest

ANSWERS = {
    "help": ["--help"],
    "run --help": ["run", "--help"],
    "publish --help": ["publish", "--help"],
    "trainings --help": ["trainings", "--help"],
    "check --help": ["check", "--help"],
    "run --jobs 0": ["run", "--estimator", "ekf", "--jobs", "0"],
}


@pytest.mark.parametrize("argv", ANSWERS.values(), ids=ANSWERS.keys())
def test_the_command_line_answers_before_loading_the_numerical_stack(benchmark, argv):
    command = [sys.executable, "-m", "kkl_bench.cli", *argv]
    answered = benchmark.pedantic(
        subprocess.run, args=(command,), kwargs={"capture_output": True}, rounds=5
    )
    assert answered.returncode in (0, 2)  # help, or the argument error
