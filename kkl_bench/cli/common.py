"""What the subcommands share when they run: name validation, the device, reading results
(their argument types and options: :mod:`kkl_bench.cli.arguments`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from kkl_bench import variants
from kkl_bench.analysis import summary
from kkl_bench.cli.arguments import PUBLISHED_RESULTS
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
