"""The ``kkl-bench`` command line.

Thin by design: each subcommand's module declares its arguments beside the
code that runs it (``add_parser``), and calls the harness, the leaderboard,
the reporting layer or the conformance kit. ``main`` only dispatches and turns
the errors a user can fix into one line and exit status 2.

Layer: the top; it may import every other layer, and none imports it.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

from kkl_bench.cli import admin, publishing, regenerate, run, tables, verify
from kkl_bench.registry import PluginLoadError, UnknownNameError
from kkl_bench.suite.task import ProfileError
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

COMMANDS = (admin, run, regenerate, tables, publishing, verify)
"""The modules that declare the subcommands (``add_parser``), in the order help lists them."""


def build_parser() -> argparse.ArgumentParser:
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
    for module in COMMANDS:
        module.add_parser(commands)
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
    args = build_parser().parse_args(argv)
    args.command_line = recorded_command(argv)
    try:
        return args.handler(args)
    except (
        UnknownNameError,
        PluginLoadError,
        ProfileError,
        ValueError,
        OSError,
        ImportError,
    ) as error:
        print(f"kkl-bench: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("kkl-bench: interrupted", file=sys.stderr)
        return 130
