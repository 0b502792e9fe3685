"""``kkl-bench list``, ``check`` and ``cache``: what is installed, whether a plugin conforms,
and the trained models on disk."""

from __future__ import annotations

import argparse

from kkl_bench import variants
from kkl_bench.cache import cache_info, clear_cache, default_cache_dir
from kkl_bench.cli.common import add_cache_argument, names
from kkl_bench.registry import estimators, regimes, systems
from kkl_bench.task import load_profiles
from kkl_bench.testing import CHECK_SYSTEMS, describe, run_checks
from kkl_bench.tracks import load_tracks


def add_parser(commands) -> None:
    listing = commands.add_parser(
        "list", help="list systems, regimes, estimators, tracks and profiles"
    )
    listing.set_defaults(handler=list_everything)

    cache = commands.add_parser("cache", help="show or clear the cache of trained models")
    cache.add_argument("action", choices=("info", "clear"))
    add_cache_argument(cache)
    cache.set_defaults(handler=manage_cache)

    check = commands.add_parser("check", help="run the conformance checks on an estimator")
    check.add_argument("estimator", metavar="NAME", help="estimator name or variant")
    check.add_argument(
        "--system",
        nargs="+",
        default=list(CHECK_SYSTEMS),
        metavar="NAME",
        help=f"systems to check on, one fit each (default: {' '.join(CHECK_SYSTEMS)}, a two- "
        "and a three-state system)",
    )
    check.set_defaults(handler=check_conformance)


def list_everything(args: argparse.Namespace) -> int:
    for registry in (systems, regimes, estimators):
        broken = registry.broken()  # imports every plugin: list only what works
        print(f"{registry.kind}s: {', '.join(registry.names())}")
        for name, reason in broken.items():
            print(f"  BROKEN {registry.kind} {name} (not usable): {reason}")
    for track in load_tracks().values():
        print(
            f"track {track.name}@v{track.version} ({len(track.tasks)} tasks x "
            f"{len(track.systems)} systems: {', '.join(track.task_names())}): {track.description}"
        )
    for profile in load_profiles().values():
        print(f"profile {profile.name}: {profile.description}")
    return 0


def manage_cache(args: argparse.Namespace) -> int:
    root = args.cache or default_cache_dir()
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
    variants.build(args.estimator)  # an unknown name is a usage error, not a failed check
    failures = passes = 0
    for system, name, error in run_checks(args.estimator, names(systems, args.system)):
        print(f"{'PASS' if error is None else 'FAIL'} {system} {name}", end="")
        print("" if error is None else f": {describe(error)}")
        failures += error is not None
        passes += error is None
    print(f"{passes} passed, {failures} failed")
    return 1 if failures else 0
