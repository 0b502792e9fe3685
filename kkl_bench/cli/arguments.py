"""The subcommands' argument types and options. Only argparse and pathlib: a command's
``--help`` reads its parser, and the parser imports nothing of what the command runs."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path


def positive_integer(what: str) -> Callable[[str], int]:
    """An argument type: a positive integer, or an error naming ``what`` and the text."""

    def parse(text: str) -> int:
        if not text.isdigit() or int(text) < 1:
            raise argparse.ArgumentTypeError(f"{what} must be a positive integer, got {text!r}")
        return int(text)

    return parse


def seed(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"seed must be a non-negative integer, got {text!r}")
    return int(text)


PUBLISHED_RESULTS = Path("leaderboard/results")
"""Where a checkout of the project holds the published board's cells."""


def add_results_argument(parser: argparse.ArgumentParser, default: Path = Path("results")) -> None:
    parser.add_argument(
        "--results",
        type=Path,
        default=default,
        metavar="DIR",
        help=f"results directory (default ./{default})",
    )


def add_jobs_argument(parser: argparse.ArgumentParser, what: str) -> None:
    """``--jobs N``: how many ``what`` run at once, in worker processes (default 1)."""
    parser.add_argument(
        "--jobs",
        type=positive_integer("jobs"),
        default=1,
        metavar="N",
        help=f"run N {what} at once (default 1)",
    )


def add_threads_argument(parser: argparse.ArgumentParser, while_: str) -> None:
    """``--threads``: the threads torch and BLAS use ``while_`` (measuring, timing)."""
    parser.add_argument(
        "--threads",
        type=positive_integer("threads"),
        default=1,
        help=f"threads while {while_} (default 1)",
    )


def add_cache_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        metavar="DIR",
        help="cache of trained models (default $KKL_BENCH_CACHE, else ./.kkl_bench_cache)",
    )


def add_reading_arguments(parser: argparse.ArgumentParser) -> None:
    """``--results``, ``--profile`` and ``--tolerate-damaged`` of the commands that read results."""
    add_results_argument(parser)
    parser.add_argument(
        "--profile", help="profile to read (default: standard if present, else the only one)"
    )
    parser.add_argument(
        "--tolerate-damaged",
        action="store_true",
        help="exit 0 even if damaged cell files were left out (they are always named)",
    )


def add_out_argument(parser: argparse.ArgumentParser, out: Path, where: str) -> None:
    parser.add_argument(
        "--out", type=Path, default=out, metavar="DIR", help=f"{where} (default {out})"
    )


def add_drawing_arguments(parser: argparse.ArgumentParser, out: Path, where: str) -> None:
    """The reading arguments and ``--out`` of the commands that draw from results."""
    add_reading_arguments(parser)
    add_out_argument(parser, out, where)
