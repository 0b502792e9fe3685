"""The ``kkl-bench`` command line.

Thin by design: each subcommand's module declares its arguments beside the
code that runs it (``add_arguments``), and calls the harness, the leaderboard,
the reporting layer or the conformance kit. ``main`` only dispatches and turns
the errors a user can fix into one line and exit status 2. Only the module of the
command given is imported (:data:`COMMANDS`), so ``kkl-bench --help``, ``--version``
and a mistyped command answer without loading torch, pandas or numba. The options
the commands share are in :mod:`~kkl_bench.cli.arguments` (argparse alone) and what
their handlers share in :mod:`~kkl_bench.cli.common`. Each handler imports the machinery
it runs when it runs, so a command's ``--help`` is as quick (all but ``verify``'s, whose
help states the verification module's tolerance).

Layer: the top; it may import every other layer, and none imports it.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shlex
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from kkl_bench.registry import PluginLoadError, UnknownNameError
from kkl_bench.support.provenance import provenance

EXAMPLES = """\
examples:
  kkl-bench list
  kkl-bench run --estimator ukf --profile quick
  kkl-bench run --estimator ekf --system duffing vdp --regime sinusoid square
  kkl-bench run --estimator all --track ood-inputs noise far-init --profile standard
  kkl-bench run --estimator dynamic_hyperkkl 'static_hyperkkl[guard=True]' --seed 0 1 2
  kkl-bench leaderboard --with-paper
  kkl-bench leaderboard --format latex > table.tex
  kkl-bench leaderboard --track far-init
  kkl-bench publish --results results --out board
  kkl-bench compare dynamic_hyperkkl autonomous_kkl --results leaderboard/results
  kkl-bench plot --results results --out figures
  kkl-bench run --estimator all --profile standard --jobs 2
  kkl-bench run --estimator ekf --executor dask --scheduler tcp://scheduler:8786
  kkl-bench cost --estimator all 'static_hyperkkl[guard=True]' --out board
  kkl-bench cache info
  kkl-bench check my_estimator --system duffing lorenz
  kkl-bench verify --sample 8
  kkl-bench regenerate --into regenerated --dry-run
  kkl-bench --version
"""

COMMANDS = {
    "list": ("admin", "list systems, regimes, estimators, tracks and profiles"),
    "cache": ("admin", "show, clear, export or import the cache of trained models"),
    "check": ("admin", "run the conformance checks on an estimator or a system"),
    "fit-times": ("admin", "record how long fits take, for the estimates of kkl-bench run"),
    "headroom": (
        "admin",
        "UKF against the particle-filter limit on a track's validation streams (for choosing "
        "a track's settings; never reads a test stream)",
    ),
    "run": ("run", "fit estimators and score them on the test sets"),
    "regenerate": (
        "regenerate",
        "compute every cell of a results folder again (resumable), into another folder",
    ),
    "leaderboard": ("tables", "print the leaderboard from stored results"),
    "compare": ("tables", "compare two estimators cell by cell with a paired bootstrap"),
    "trainings": (
        "tables",
        "how the learned rows' trainings ended: steps, why they stopped, the step kept",
    ),
    "publish": (
        "publishing",
        "write a leaderboard folder (README, LaTeX, CSV, figures, index.html) from results",
    ),
    "plot": ("publishing", "draw the figures from stored results (PNG and SVG)"),
    "scaling": (
        "publishing",
        "the Lorenz-96 scaling study: fit time, online cost and RMSE against n",
    ),
    "throughput": (
        "publishing",
        "what each learned row's training achieves: samples/s and GFLOP/s over the peak",
    ),
    "cost": (
        "publishing",
        "time every estimator's estimate side by side on the paper track (cost.csv)",
    ),
    "verify": ("verify", "re-derive published cells at the current commit and compare them"),
}
"""Each subcommand, in the order help lists them: the module of :mod:`kkl_bench.cli` whose
``add_arguments`` declares its arguments and handler, and the line help lists it with."""


def build_parser(argv: Sequence[str] = ()) -> argparse.ArgumentParser:
    """The parser of ``kkl-bench`` for the command line ``argv``: every subcommand is
    listed, and the one ``argv`` names (its first word that is not an option), if any,
    is declared in full by its module, which only then is imported."""
    parser = argparse.ArgumentParser(
        prog="kkl-bench",
        description="Benchmark state observers of nonlinear systems driven by exogenous inputs.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--version",
        action=_Version,
        help="print the versions and the git commit a cell of this installation records, and exit",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parsers = {  # the line is each one's description too, unless its module gives a longer one
        name: commands.add_parser(name, help=line, description=line)
        for name, (_, line) in COMMANDS.items()
    }
    given = next((word for word in argv if not word.startswith("-")), None)
    if given in COMMANDS:
        module = COMMANDS[given][0]
        importlib.import_module(f"kkl_bench.cli.{module}").add_arguments(
            {name: parsers[name] for name, (owner, _) in COMMANDS.items() if owner == module}
        )
    return parser


def version_text() -> str:
    """What ``kkl-bench --version`` prints: the fields of :func:`provenance` that every
    cell records, so an installation can be compared with the cells of a board: the
    package's version and git commit (``-dirty`` if modified) on the first line, then
    the other packages, Python and the platform."""
    recorded = provenance()
    versions = dict(recorded["versions"])
    commit = recorded["git_commit"] or "not a git checkout"
    first = f"kkl-bench {versions.pop('kkl-bench', 'not installed')} (git {commit})"
    packages = ", ".join(f"{name} {number}" for name, number in versions.items())
    return f"{first}\n{packages}; Python {recorded['python']} on {recorded['platform']}"


class _Version(argparse.Action):
    """``--version``: prints :func:`version_text` and exits, computed only when asked."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(version_text())
        parser.exit()


def recorded_command(argv: Sequence[str], cwd: Path | None = None) -> str:
    """The command line a run's cells record: ``kkl-bench`` and ``argv`` as given, except
    that an absolute path (an argument, or the value of ``--option=PATH``) is written
    relative to the working directory ``cwd`` when it lies inside it (the same command
    run from there) and as ``<...>/NAME`` when it lies outside, so that no record, and no
    board that prints it, names a path of one machine."""
    cwd = Path.cwd() if cwd is None else cwd

    def portable(token: str) -> str:
        option, equals, value = token.partition("=") if token.startswith("--") else ("", "", token)
        path = Path(value)
        if not path.is_absolute():
            return token
        rendered = str(path.relative_to(cwd)) if path.is_relative_to(cwd) else f"<...>/{path.name}"
        return f"{option}{equals}{rendered}"

    return shlex.join(["kkl-bench", *map(portable, argv)])


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    args.command_line = recorded_command(argv)
    try:
        return args.handler(args)
    except BrokenPipeError:
        return _reader_gone()
    except (
        UnknownNameError,
        PluginLoadError,
        ValueError,
        OSError,
        ImportError,
    ) as error:
        print(f"kkl-bench: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("kkl-bench: interrupted", file=sys.stderr)
        return 130


def _reader_gone() -> int:
    """The reader of standard output closed it (``kkl-bench leaderboard | head``): stop
    quietly with the exit status of a process SIGPIPE ended, as other Unix tools do. What
    is still buffered goes nowhere, instead of failing again when Python flushes it at
    exit (the Python documentation's recipe, "Note on SIGPIPE")."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 128 + signal.SIGPIPE
