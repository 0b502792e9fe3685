"""``kkl-bench list``, ``check``, ``cache``, ``fit-times`` and ``headroom``: what is installed,
whether a plugin conforms, the trained models on disk, how long fits take, and how far a
track's tasks put the UKF from the Bayes limit.

Each handler imports what it runs (the plugins, pandas, the conformance kit),
not the module: ``--help`` and an argument error answer at once.
"""

from __future__ import annotations

import argparse
import importlib.resources
from pathlib import Path

from kkl_bench.cli.arguments import add_cache_argument
from kkl_bench.registry import estimators, regimes, systems
from kkl_bench.support.cache import cache_info, carry_models, clear_cache, default_cache_dir


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    listing = parsers["list"]
    listing.set_defaults(handler=list_everything)

    cache = parsers["cache"]
    cache.description = (
        "info: what the cache holds; clear: delete it; export FOLDER: copy its "
        "trained models (checksummed, never over an intact one) into FOLDER, e.g. one that travels "
        "to another machine with a long regeneration; import FOLDER: copy them from FOLDER "
        "into the cache. The checkpoints of trainings under way travel with "
        "--with-checkpoints (an export makes FOLDER's the cache's own: newer ones replace "
        "older, a finished training's are dropped; an import keeps those already in the "
        "cache); kernels compiled for one machine never do."
    )
    cache.add_argument("action", choices=("info", "clear", "export", "import"))
    cache.add_argument("folder", nargs="?", type=Path, help="for export and import")
    cache.add_argument(
        "--with-checkpoints",
        action="store_true",
        help="also carry the checkpoints of trainings under way (a killed training resumes)",
    )
    add_cache_argument(cache)
    cache.set_defaults(handler=manage_cache)

    check = parsers["check"]
    check.description = (
        "Run the conformance kit on an estimator (fitted on the quick profile's "
        "budget, updated with the estimator's check_budget) or, given a system's name, the "
        "system checks (shapes, Jacobians against finite differences, torch tensors, finite "
        "trajectories)."
    )
    check.add_argument(
        "estimator", metavar="NAME", help="estimator name or variant, or a system's name"
    )
    check.add_argument(
        "--system",
        nargs="+",
        metavar="NAME",
        help="systems to check on, one fit each (default: the kit's two-state and three-state "
        "systems, or, for an estimator that supports neither, the first two registered "
        "systems it supports; the checks print each one's name)",
    )
    check.set_defaults(handler=check_conformance)

    times = parsers["fit-times"]
    times.description = (
        "Measure, per profile, row and system, the median training seconds of "
        "the fits behind the cells of each RESULTS folder and their scoring seconds per cell, "
        "and merge them into --out (default: the table the package ships, which "
        "`kkl-bench run` estimates from where its own results folder has no record)."
    )
    times.add_argument("--results", type=Path, nargs="+", required=True, metavar="DIR")
    times.add_argument(
        "--out",
        type=Path,
        metavar="CSV",
        help="the table to merge into (default: the one the package ships)",
    )
    times.set_defaults(handler=record_fit_times)

    room = parsers["headroom"]
    room.add_argument("--track", required=True, metavar="NAME", help="track to measure")
    room.add_argument("--system", nargs="+", metavar="NAME", help="systems (default: all)")
    room.add_argument("--regime", nargs="+", metavar="NAME", help="tasks (default: all)")
    room.add_argument(
        "--trajectories", type=int, default=4, help="validation trajectories per task (4)"
    )
    room.add_argument(
        "--limit",
        default="particle_filter[n=2000]",
        metavar="NAME",
        help="the limit row's estimator (default: particle_filter[n=2000])",
    )
    room.set_defaults(handler=measure_headroom)


def list_everything(args: argparse.Namespace) -> int:
    from kkl_bench.measurement import sensors
    from kkl_bench.suite.task import load_profiles
    from kkl_bench.suite.tracks import broken_tracks, load_tracks

    for registry in (systems, regimes, sensors, estimators):
        broken = registry.broken()  # imports every plugin: list only what works
        listed = registry.names()
        if registry is estimators:  # with the family each declares (kkl_bench.families)
            listed = [f"{name} ({_family_label(estimators.get(name))})" for name in listed]
        print(f"{registry.kind}s: {', '.join(listed)}")
        for name, reason in broken.items():
            print(f"  BROKEN {registry.kind} {name} (not usable): {reason}")
    for source, reason in broken_tracks().items():
        print(f"  BROKEN track file {source} (not usable): {reason}")
    for track in load_tracks().values():
        print(
            f"track {track.name}@v{track.version} ({len(track.tasks)} tasks x "
            f"{len(track.systems)} systems: {', '.join(track.task_names())}): {track.description}"
        )
    for profile in load_profiles().values():
        print(f"profile {profile.name}: {profile.description}")
    return 0


def _family_label(cls: type) -> str:
    """``model-based``, or ``learned, undeclared`` for an estimator that declares none."""
    from kkl_bench import families

    family = families.estimator_family(cls)
    return family if families.declared_family(cls) else f"{family}, undeclared"


def manage_cache(args: argparse.Namespace) -> int:
    root = args.cache or default_cache_dir()
    carrying = args.action in ("export", "import")
    if carrying != (args.folder is not None):
        needs = "needs a FOLDER" if carrying else "takes no FOLDER (export and import do)"
        raise ValueError(f"kkl-bench cache {args.action} {needs}")
    if carrying:
        exporting = args.action == "export"
        source, destination = (root, args.folder) if exporting else (args.folder, root)
        if not Path(source).is_dir():
            raise ValueError(f"nothing to {args.action}: {source} is not a folder")
        carried = carry_models(source, destination, args.with_checkpoints, snapshot=exporting)
        print(
            f"{args.action}ed {carried.copied} model{'s' * (carried.copied != 1)} "
            f"({carried.size_bytes / 1e6:.1f} MB) from "
            f"{source} to {destination}; {carried.present} already there"
            + (f"; {carried.left} left (damaged, or being written)" if carried.left else "")
            + (
                f"; dropped {carried.dropped} checkpoint{'s' * (carried.dropped != 1)} of "
                "finished trainings"
                if carried.dropped
                else ""
            )
        )
        return 0
    if args.action == "clear":
        print(f"removed {root} ({clear_cache(root) / 1e6:.1f} MB)")
        return 0
    kinds = cache_info(root)
    print(f"cache: {root.resolve()}")
    if not kinds:
        print("  (empty)")
    for kind in kinds:
        damaged = f", {kind.damaged} damaged (rebuilt on next use)" if kind.damaged else ""
        print(f"  {kind.kind}: {kind.entries} entries, {kind.size_bytes / 1e6:.1f} MB{damaged}")
    return 0


def check_conformance(args: argparse.Namespace) -> int:
    from kkl_bench import variants
    from kkl_bench.cli.common import names
    from kkl_bench.testing import describe, run_checks
    from kkl_bench.testing.systems import run_system_checks

    if args.estimator in systems and args.estimator not in estimators:
        if args.system:
            raise ValueError(
                f"--system is for an estimator's checks; {args.estimator!r} is a system"
            )
        outcomes = (
            (args.estimator, name, error) for name, error in run_system_checks(args.estimator)
        )
    else:
        variants.build(args.estimator)  # an unknown name is a usage error, not a failed check
        checked = names(systems, args.system) if args.system else None
        outcomes = run_checks(args.estimator, checked)
    failures = passes = 0
    for system, name, error in outcomes:
        print(f"{'PASS' if error is None else 'FAIL'} {system} {name}", end="")
        print("" if error is None else f": {describe(error)}")
        failures += error is not None
        passes += error is None
    print(f"{passes} passed, {failures} failed")
    return 1 if failures else 0


def record_fit_times(args: argparse.Namespace) -> int:
    import pandas as pd

    from kkl_bench.run import fit_times
    from kkl_bench.run.results import load_results

    out = args.out or Path(str(importlib.resources.files("kkl_bench").joinpath(fit_times.SHIPPED)))
    measured = pd.concat([fit_times.measure(load_results(folder)) for folder in args.results])
    table = fit_times.merge_into(out, measured)
    print(f"{len(measured)} rows measured; {out} holds {len(table)}")
    return 0


def measure_headroom(args: argparse.Namespace) -> int:
    from kkl_bench.analysis.headroom import headroom
    from kkl_bench.suite.task import Task
    from kkl_bench.suite.tracks import get_track

    track = get_track(args.track)
    for name in (args.system or []) + (args.regime or []):
        if name not in track.systems and name not in track.task_names():
            raise ValueError(
                f"{name!r} is neither a system ({', '.join(track.systems)}) nor a task "
                f"({', '.join(track.task_names())}) of track {track.name!r}"
            )
    print(f"{'task':<40} {'UKF':>9} {'limit':>9} {'UKF / limit':>12}")
    for task_name in args.regime or track.task_names():
        for system in args.system or track.systems:
            task = Task(system, task_name, track.version, track.name)
            result = headroom(task, args.trajectories, args.limit)
            print(
                f"{task.id:<40} {result.ukf_rmse:>9.4g} {result.limit_rmse:>9.4g} "
                f"{result.ratio:>12.3f}",
                flush=True,
            )
    return 0
