"""The ``kkl-bench`` command line: list, run, leaderboard, check.

Thin by design: it parses arguments and calls the harness, the leaderboard
and the conformance kit.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from kkl_bench import harness, leaderboard, variants
from kkl_bench import status as job_status
from kkl_bench.cache import cache_info, clear_cache, default_cache_dir
from kkl_bench.devices import DEVICES
from kkl_bench.devices import resolve as resolve_device
from kkl_bench.executors import EXECUTORS
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import PluginLoadError, UnknownNameError, estimators, regimes, systems
from kkl_bench.results import DamagedCellError, load_results, provenance
from kkl_bench.significance import MARGIN
from kkl_bench.task import ProfileError, get_profile, load_profiles
from kkl_bench.testing import CHECK_SYSTEMS
from kkl_bench.tracks import get_track, load_tracks

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
  kkl-bench publish --results leaderboard/results --out leaderboard
  kkl-bench compare dynamic_hyperkkl autonomous_kkl --results leaderboard/results
  kkl-bench plot --results results --out figures
  kkl-bench run --estimator all --profile standard --jobs 2
  kkl-bench run --estimator ekf --executor dask --scheduler tcp://scheduler:8786
  kkl-bench cost --estimator all 'static_hyperkkl[guard=True]' --out leaderboard
  kkl-bench cache info
  kkl-bench check my_estimator
"""


def _names(registry, requested: Sequence[str] | None) -> tuple[str, ...]:
    """``requested`` validated against ``registry``; ``None`` means every name, and ``all``
    among others stands for every name in its place (``all 'static_hyperkkl[guard=True]'``).

    Estimators may be variants (``static_hyperkkl[guard=True]``), returned canonical.
    """
    if not requested:
        return tuple(registry.names())
    requested = [name for entry in requested for name in _expand_all(registry, entry)]
    if registry is estimators:
        return tuple(dict.fromkeys(variants.canonical(name) for name in requested))
    for name in requested:
        registry.get(name)  # raises an error that lists the valid names
    return tuple(dict.fromkeys(requested))


def _expand_all(registry, entry: str) -> list[str]:
    return list(registry.names()) if entry == "all" else [entry]


def _jobs(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"jobs must be a positive integer, got {text!r}")
    return int(text)


def _seed(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"seed must be a non-negative integer, got {text!r}")
    return int(text)


def _add_results_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results",
        type=Path,
        default=Path("results"),
        metavar="DIR",
        help="results directory (default ./results)",
    )


def _add_cache_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        metavar="DIR",
        help="cache of trained models (default $KKL_BENCH_CACHE, else ./.kkl_bench_cache)",
    )


def _add_reading_arguments(parser: argparse.ArgumentParser) -> None:
    """``--results``, ``--profile`` and ``--tolerate-damaged`` of the commands that read results."""
    _add_results_argument(parser)
    parser.add_argument(
        "--profile", help="profile to read (default: standard if present, else the only one)"
    )
    parser.add_argument(
        "--tolerate-damaged",
        action="store_true",
        help="exit 0 even if damaged cell files were left out (they are always named)",
    )


def _add_out_argument(parser: argparse.ArgumentParser, out: Path, where: str) -> None:
    parser.add_argument(
        "--out", type=Path, default=out, metavar="DIR", help=f"{where} (default {out})"
    )


def _add_drawing_arguments(parser: argparse.ArgumentParser, out: Path, where: str) -> None:
    """The reading arguments and ``--out`` of the commands that draw from results."""
    _add_reading_arguments(parser)
    _add_out_argument(parser, out, where)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kkl-bench",
        description="Benchmark state observers of nonlinear systems driven by exogenous inputs.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    commands.add_parser("list", help="list systems, regimes, estimators, tracks and profiles")

    run = commands.add_parser(
        "run",
        help="fit estimators and score them on the test sets",
        description="Fit each estimator once per system, score it on every regime's test set, "
        "and write one result file per cell. Cells already on disk are skipped (use --force).",
    )
    run.add_argument(
        "--estimator",
        nargs="+",
        required=True,
        metavar="NAME",
        help="estimator names, variants such as 'static_hyperkkl[guard=True]', or 'all'",
    )
    run.add_argument("--system", nargs="+", metavar="NAME", help="systems to run (default: all)")
    run.add_argument(
        "--track",
        nargs="+",
        default=[PAPER_TRACK],
        metavar="NAME",
        help="tracks to score on, or 'all' (default: paper); estimators are fitted once "
        "and scored on every track",
    )
    run.add_argument(
        "--regime",
        nargs="+",
        metavar="NAME",
        help="tasks of the tracks to score, e.g. sinusoid or chirp (default: all)",
    )
    run.add_argument("--profile", default="quick", help="profile: quick (default) or standard")
    run.add_argument(
        "--seed",
        type=_seed,
        nargs="+",
        default=[0],
        metavar="SEED",
        help="training seeds, one fit per seed (default 0); estimators that ignore "
        "the seed (the filters) run with the first only",
    )
    _add_results_argument(run)
    _add_cache_argument(run)
    run.add_argument(
        "--jobs",
        type=_jobs,
        default=1,
        metavar="N",
        help="run N (estimator, system) jobs at once (default 1)",
    )
    run.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="loky",
        help="loky: local worker processes (default); dask: a Dask cluster (see --scheduler)",
    )
    run.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="Dask scheduler address, e.g. tcp://10.0.0.5:8786 (default: start a LocalCluster of --jobs workers)",
    )
    run.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where torch estimators train: auto (default: cuda if torch sees a GPU, else "
        "cpu), cpu or cuda; models are cached as CPU tensors and estimates run on the CPU",
    )
    run.add_argument("--force", action="store_true", help="recompute cells already on disk")

    board = commands.add_parser("leaderboard", help="print the leaderboard from stored results")
    board.add_argument("--format", choices=leaderboard.FORMATS, default="markdown")
    _add_reading_arguments(board)
    board.add_argument(
        "--track",
        default=PAPER_TRACK,
        metavar="NAME",
        help="the track to tabulate (default: paper), or 'summary' for every track's RMSE "
        "relative to the paper track's",
    )
    board.add_argument(
        "--with-paper",
        action="store_true",
        help="add the HyperKKL paper's numbers as reference rows",
    )
    board.add_argument(
        "--by-version",
        action="store_true",
        help="tabulate cells of different protocol or KKL toolkit versions as separate, "
        "labelled groups (default: refuse to mix them)",
    )
    board.add_argument(
        "--details",
        action="store_true",
        help="append fit time, estimation cost and NRMSE per estimator and system (markdown)",
    )

    versus = commands.add_parser(
        "compare",
        help="compare two estimators cell by cell with a paired bootstrap",
        description="Per cell: the ratio of A's mean RMSE to B's, its 90 %% interval from the "
        "paired hierarchical bootstrap (test trajectories and seeds resampled) and the verdict "
        "of one-sided tests at 5 %%.",
    )
    versus.add_argument("a", metavar="A", help="estimator (or variant) name")
    versus.add_argument("b", metavar="B", help="estimator (or variant) name")
    _add_reading_arguments(versus)
    versus.add_argument(
        "--track", default=PAPER_TRACK, metavar="NAME", help="the track (default: paper)"
    )

    publish = commands.add_parser(
        "publish",
        help="write a leaderboard folder (README, LaTeX, CSV, figures, index.html) from results",
        description="Write the leaderboard folder from stored results alone: README.md with "
        "the tables, LaTeX, CSV, figures (needs matplotlib: pip install 'kkl-bench[plot]') "
        "and a static index.html. The same results give byte-identical files.",
    )
    _add_drawing_arguments(publish, Path("leaderboard"), "the folder to write")
    publish.add_argument(
        "--margin",
        type=float,
        default=MARGIN,
        help=f"practical-equivalence margin of the bold marks: a win must be by more than "
        f"this fraction (default {MARGIN:g})",
    )
    publish.add_argument(
        "--force",
        action="store_true",
        help="replace a board of another profile or results folder in --out (default: refuse)",
    )

    plot = commands.add_parser(
        "plot",
        help="draw the figures from stored results (PNG and SVG)",
        description="Per (system, regime) the states and error norm on test trajectory 0, "
        "a heat map of RMSE relative to the UKF, and cost against RMSE. "
        "Needs matplotlib: pip install 'kkl-bench[plot]'.",
    )
    _add_drawing_arguments(plot, Path("."), "figures go to DIR/figures/")

    scaling = commands.add_parser(
        "scaling",
        help="the Lorenz-96 scaling study: fit time, online cost and RMSE against n",
        description="From the more-systems cells of Lorenz-96 (n = 5, 10, 20, 40) and the "
        "models their run cached, time every fitted estimator's estimate side by side "
        "(batch 20 and 1, one thread) and write scaling.md, scaling.csv and "
        "figures/scaling.png|svg with the fitted exponent of each cost. Run "
        "`kkl-bench run --track more-systems --estimator all` first, with the same --cache.",
    )
    _add_drawing_arguments(scaling, Path("leaderboard"), "the folder to write")
    _add_cache_argument(scaling)
    scaling.add_argument(
        "--seed", type=_seed, default=0, help="the training seed whose models are timed (default 0)"
    )
    scaling.add_argument(
        "--missing-only",
        action="store_true",
        help="time only the fitted (estimator, n) that the study in --out has no online cost "
        "for, beside the EKF at the same sizes, and keep the other rows' costs (to add an "
        "estimator or a size without fitting the rest again)",
    )

    cost = commands.add_parser(
        "cost",
        help="time every estimator's estimate side by side on the paper track (cost.csv)",
        description="Load each estimator's trained models from the cache (fitting them if "
        "missing), then time its estimate on every test set of the chosen tracks, all "
        "estimators and the EKF beside them in turn in one process, on --threads threads, "
        "best of --rounds. Merges the rows into DIR/cost.csv (the other rows keep their own "
        "runs; --replace rewrites it), which `kkl-bench publish` shows in the cost table in "
        "place of the times the scoring runs measured (those come from many runs and "
        "machine loads).",
    )
    cost.add_argument(
        "--estimator",
        nargs="+",
        default=["all"],
        metavar="NAME",
        help="estimators or variants to time, or 'all' (default)",
    )
    cost.add_argument("--system", nargs="+", metavar="NAME", help="systems (default: all)")
    cost.add_argument(
        "--track", nargs="+", default=["paper"], help="tracks whose test sets are timed"
    )
    cost.add_argument("--profile", default="standard", help="profile (default standard)")
    cost.add_argument(
        "--seed", type=_seed, default=0, help="the training seed whose models are timed (default 0)"
    )
    cost.add_argument("--rounds", type=_jobs, default=3, help="timings per call (default 3)")
    cost.add_argument("--threads", type=_jobs, default=1, help="threads while timing (default 1)")
    cost.add_argument(
        "--max-seconds",
        type=float,
        default=10.0,
        help="stop timing a call once its timings add up to this (default 10)",
    )
    cost.add_argument(
        "--replace",
        action="store_true",
        help="rewrite cost.csv with this run's rows only (default: merge them into it)",
    )
    _add_out_argument(cost, Path("leaderboard"), "the folder whose cost.csv to merge into")
    _add_cache_argument(cost)

    cache = commands.add_parser("cache", help="show or clear the cache of trained models")
    cache.add_argument("action", choices=("info", "clear"))
    _add_cache_argument(cache)

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
    return parser


def _list() -> int:
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


def _run(args: argparse.Namespace) -> int:
    spec = harness.RunSpec(
        estimators=_names(estimators, args.estimator),
        systems=_names(systems, args.system),
        regimes=tuple(dict.fromkeys(args.regime)) if args.regime else None,
        tracks=tuple(load_tracks()) if args.track == ["all"] else tuple(args.track),
        profile=get_profile(args.profile),
        seeds=tuple(args.seed),
        results_dir=args.results,
        cache_dir=args.cache or default_cache_dir(),
        force=args.force,
        device=args.device,
        command=args.command_line,
    )
    if args.scheduler is None:  # local workers: a missing GPU is an error before any work
        resolve_device(args.device)
    total = sum(len(spec.seeds_for(name)) for name in spec.estimators) * len(spec.tasks())
    with (
        tqdm(
            total=total, unit="cell", desc="kkl-bench", dynamic_ncols=True, mininterval=1.0
        ) as bar,
        _showing_jobs(bar, spec.results_dir / ".claims" / spec.profile.name),
    ):

        def progress(cell, status):
            if status == "error":
                tqdm.write(f"error in {cell.estimator} {cell.task}: {cell.error.splitlines()[-1]}")
            bar.update()

        try:
            summary = harness.run(
                spec, progress, jobs=args.jobs, executor=args.executor, scheduler=args.scheduler
            )
        except KeyboardInterrupt:
            print(f"kkl-bench: interrupted; {RESUME}", file=sys.stderr)
            return 130
    print(
        f"{len(summary.scored)} cells scored, {len(summary.cached)} already done, "
        f"{len(summary.failed)} failed; results in {spec.results_dir}/{spec.profile.name}/"
        + (f"; {RESUME}" if summary.failed else "")
    )
    return 0 if summary.ok else 1


RESUME = (
    "every finished cell is saved; run the same command again to resume (finished cells "
    "are skipped, failed and missing ones computed)"
)


@contextlib.contextmanager
def _showing_jobs(bar: tqdm, claims: Path, every_s: float = 1.0) -> Iterator[None]:
    """Show beside ``bar``, every ``every_s`` seconds, what each running job says it does
    (:mod:`kkl_bench.status`): which estimator fits or scores on which system, and how
    far its training is."""
    since, stop = time.time() - 1.0, threading.Event()

    def show() -> None:
        while not stop.wait(every_s):
            bar.set_postfix_str(" | ".join(job_status.current(claims, since)) or "")

    thread = threading.Thread(target=show, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        bar.set_postfix_str("")


def _load(
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
        raise ValueError(f"no results under {args.results}/; run `kkl-bench run` first")
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
        leaderboard.check_not_mixed(results)
    return results, damaged


def _status(args: argparse.Namespace, damaged: list[DamagedCellError]) -> int:
    """1 if damaged cells were left out (unless tolerated), else 0."""
    if damaged and not args.tolerate_damaged:
        print(
            f"kkl-bench: {len(damaged)} damaged cell file(s) left out; `kkl-bench run` with the "
            "same arguments recomputes them (--tolerate-damaged exits 0)",
            file=sys.stderr,
        )
        return 1
    return 0


def _leaderboard(args: argparse.Namespace) -> int:
    results, damaged = _load(args, check_versions=not args.by_version)
    if args.track == "summary":
        frame = leaderboard.track_summary(results)
        print(
            frame.to_csv(index=False, float_format="%.6g")
            if args.format == "csv"
            else leaderboard.render_track_summary(frame)
        )
        return _status(args, damaged)
    settling = get_track(args.track).settling
    results = _of_track(results, args.track)
    with_paper = args.with_paper and args.track == PAPER_TRACK
    if args.format == "markdown":
        smoke = args.profile in load_profiles() and get_profile(args.profile).smoke
        print(leaderboard.caption(args.track, args.profile, smoke, settling))
    for label, cells in leaderboard.version_groups(results).items():
        if label:
            print(f"\n{label}\n" if args.format == "markdown" else f"# {label}")
        summary = leaderboard.summary_table(cells, with_paper=with_paper)
        print(leaderboard.render(summary, args.format, settling=settling), end="")
        if args.details:
            print("\n" + leaderboard.cost_table(summary))
    return _status(args, damaged)


def _of_track(results: pd.DataFrame, track: str) -> pd.DataFrame:
    """The cells of ``track``; the error names the tracks the results hold."""
    selected = results[results["track"] == track]
    if selected.empty:
        raise ValueError(
            f"no results for track {track!r}; the results hold "
            f"{', '.join(sorted(set(results['track'])))} (run with --track {track})"
        )
    return selected


def _compare(args: argparse.Namespace) -> int:
    results, damaged = _load(args)
    results = _of_track(results, args.track)
    print(leaderboard.comparison_table(leaderboard.summary_table(results), args.a, args.b))
    return _status(args, damaged)


def _publish(args: argparse.Namespace) -> int:
    from kkl_bench.publish import publish

    results, damaged = _load(args)
    written = publish(results, args.results, args.out, args.margin, args.force)
    print(f"wrote {len(written)} files to {args.out}/")
    return _status(args, damaged)


def _plot(args: argparse.Namespace) -> int:
    from kkl_bench.publish import draw_figures

    results, damaged = _load(args)
    summary = leaderboard.summary_table(_of_track(results, PAPER_TRACK))
    names = draw_figures(summary, args.results, args.profile, args.out)
    print(f"wrote {2 * len(names)} figures to {args.out / 'figures'}/")
    return _status(args, damaged)


def _scaling(args: argparse.Namespace) -> int:
    from kkl_bench import scaling

    results, damaged = _load(args)
    cells = scaling.cell_summary(results)
    profile = results["profile"].iloc[0]
    spec = harness.RunSpec(
        estimators=tuple(sorted(set(cells["estimator"]))),
        systems=tuple(scaling.system_name(n) for n in sorted(set(cells["n"]))),
        regimes=(scaling.REGIME,),
        tracks=(scaling.TRACK,),
        profile=get_profile(profile),
        cache_dir=args.cache or default_cache_dir(),
    )
    study = args.out / "scaling.csv"
    stored = scaling.stored_timings(study if args.missing_only else None)
    wanted = scaling.untimed(cells, stored)
    fitted = {
        (estimator, n): scaling.fit_from_cache(spec, estimator, n, args.seed)
        for estimator, n in tqdm(wanted, desc="loading fitted models", unit="model")
    }
    if fitted:
        commit = provenance()["git_commit"]
        timings = scaling.timing_frame(scaling.time_estimators(spec, fitted), commit)
        stored = scaling.add_timings(stored, timings)
    else:
        print(f"every fitted estimator already has its online cost in {study}")
    written = scaling.write_study(cells, stored, profile, args.out)
    print(f"wrote {', '.join(map(str, written))}")
    return _status(args, damaged)


def _cost(args: argparse.Namespace) -> int:
    from kkl_bench import cost

    spec = harness.RunSpec(
        estimators=_names(estimators, args.estimator),
        systems=_names(systems, args.system),
        regimes=None,
        tracks=tuple(args.track),
        profile=get_profile(args.profile),
        seeds=(args.seed,),
        cache_dir=args.cache or default_cache_dir(),
    )
    out = args.out / cost.COST_FILE
    rows = cost.measure(spec, out, args.rounds, args.threads, args.max_seconds, args.replace)
    print(leaderboard.measured_cost_table(rows))
    kept = len(cost.read_costs(out)) - len(rows)
    print(
        f"wrote {len(rows)} rows (run {rows['run'].iloc[0]}) to {out}; {kept} rows of earlier runs kept"
    )
    return 0


def _cache(args: argparse.Namespace) -> int:
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


def _check(args: argparse.Namespace) -> int:
    from kkl_bench.testing import describe, run_checks

    variants.build(args.estimator)  # an unknown name is a usage error, not a failed check
    checked = _names(systems, args.system)
    failures = passes = 0
    for system, name, error in run_checks(args.estimator, checked):
        print(f"{'PASS' if error is None else 'FAIL'} {system} {name}", end="")
        print("" if error is None else f": {describe(error)}")
        failures += error is not None
        passes += error is None
    print(f"{passes} passed, {failures} failed")
    return 1 if failures else 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.command_line = shlex.join(["kkl-bench", *argv])
    commands = {
        "list": lambda: _list(),
        "run": lambda: _run(args),
        "leaderboard": lambda: _leaderboard(args),
        "cache": lambda: _cache(args),
        "compare": lambda: _compare(args),
        "publish": lambda: _publish(args),
        "plot": lambda: _plot(args),
        "scaling": lambda: _scaling(args),
        "cost": lambda: _cost(args),
        "check": lambda: _check(args),
    }
    try:
        return commands[args.command]()
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


if __name__ == "__main__":
    sys.exit(main())
