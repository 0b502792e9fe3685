"""What the subcommands share: name validation, argument types and options, reading results."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

from kkl_bench import variants
from kkl_bench.analysis import summary
from kkl_bench.registry import estimators
from kkl_bench.run.results import DamagedCellError, load_results
from kkl_bench.support.devices import resolve as resolve_device


def device_before_work(args: argparse.Namespace) -> str | None:
    """Where ``--device`` has torch estimators train: resolved now for local workers (``cpu``
    or ``cuda``; a missing GPU is an error before any work), or, with a Dask scheduler,
    ``args.device`` unless it is ``auto``, which each worker resolves (None)."""
    if args.scheduler is None:
        return resolve_device(args.device)
    return None if args.device == "auto" else args.device


def names(registry, requested: Sequence[str] | None) -> tuple[str, ...]:
    """``requested`` validated against ``registry``; ``None`` means every name, and ``all``
    among others stands for every name in its place (``all 'static_hyperkkl[guard=True]'``).

    Estimators may be variants (``static_hyperkkl[guard=True]``), returned canonical; each
    is built once here, so a bad hyperparameter value (``enkf[n=-3]``) is an error before
    any work starts.
    """
    if not requested:
        return tuple(registry.names())
    requested = [
        name for entry in requested for name in (registry.names() if entry == "all" else [entry])
    ]
    if registry is estimators:
        canonical = tuple(dict.fromkeys(variants.canonical(name) for name in requested))
        for name in canonical:
            variants.build(variants.split_row(name)[0])  # raises ValueError naming the value
        return canonical
    for name in requested:
        registry.get(name)  # raises an error that lists the valid names
    return tuple(dict.fromkeys(requested))


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


def load(
    args: argparse.Namespace, check_versions: bool = True
) -> tuple[pd.DataFrame, list[DamagedCellError]]:
    """The results of the chosen profile and the damaged cell files left out (each warned of).

    Without ``--profile``: ``standard`` if present, else the only profile.
    With ``check_versions``, cells of different protocol or toolkit versions
    are refused (``ValueError`` naming them).
    """
    damaged: list[DamagedCellError] = []
    results = load_results(args.results, damaged)
    for error in damaged:
        print(f"kkl-bench: warning: left out {error}", file=sys.stderr)
    if results.empty:
        published = (
            f"; the published board's are in {PUBLISHED_RESULTS}/ (--results {PUBLISHED_RESULTS})"
            if PUBLISHED_RESULTS.is_dir() and Path(args.results) != PUBLISHED_RESULTS
            else ""
        )
        raise ValueError(f"no results under {args.results}/; run `kkl-bench run` first{published}")
    profiles = sorted(set(results["profile"]))
    profile = args.profile or ("standard" if "standard" in profiles else profiles[0])
    if profile not in profiles:
        raise ValueError(
            f"no results for profile {profile!r} in {args.results}/; found: {', '.join(profiles)}"
        )
    if args.profile is None and len(profiles) > 1:
        print(
            f"(profile {profile}; results also hold {', '.join(p for p in profiles if p != profile)})",
            file=sys.stderr,
        )
    args.profile = profile
    results = results[results["profile"] == profile]
    if check_versions:
        summary.check_not_mixed(results)
    return results, damaged


def exit_status(args: argparse.Namespace, damaged: list[DamagedCellError]) -> int:
    """1 if damaged cells were left out (unless tolerated), else 0."""
    if damaged and not args.tolerate_damaged:
        print(
            f"kkl-bench: {len(damaged)} damaged cell file(s) left out; `kkl-bench run` with the "
            "same arguments recomputes them (--tolerate-damaged exits 0)",
            file=sys.stderr,
        )
        return 1
    return 0


def of_track(results: pd.DataFrame, track: str) -> pd.DataFrame:
    """The cells of ``track``; the error names the tracks the results hold."""
    selected = results[results["track"] == track]
    if selected.empty:
        raise ValueError(
            f"no results for track {track!r}; the results hold "
            f"{', '.join(sorted(set(results['track'])))} (run with --track {track})"
        )
    return selected
