"""``kkl-bench publish``, ``plot``, ``scaling``, ``throughput`` and ``cost``: the published
folder and what feeds it.

Each handler imports what it runs (the harness, the analysis, the report), not the module:
``--help`` and an argument error answer at once.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from kkl_bench.analysis.significance import MARGIN
from kkl_bench.cli.arguments import (
    add_cache_argument,
    add_drawing_arguments,
    add_out_argument,
    add_threads_argument,
    positive_integer,
    seed,
)
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import estimators, systems
from kkl_bench.support.cache import default_cache_dir
from kkl_bench.support.device_names import DEVICES
from kkl_bench.support.provenance import provenance


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    publish = parsers["publish"]
    publish.description = (
        "Write the leaderboard folder from stored results alone: README.md with "
        "the tables, LaTeX, CSV, figures (needs matplotlib: pip install 'kkl-bench[plot]') "
        "and a static index.html. The same results give byte-identical files."
    )
    add_drawing_arguments(publish, Path("leaderboard"), "the folder to write")
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
    publish.set_defaults(handler=publish_folder)

    plot = parsers["plot"]
    plot.description = (
        "Per (system, regime) the states and error norm on test trajectory 0, "
        "a heat map of RMSE relative to the UKF, and cost against RMSE. "
        "Needs matplotlib: pip install 'kkl-bench[plot]'."
    )
    add_drawing_arguments(plot, Path("."), "figures go to DIR/figures/")
    plot.set_defaults(handler=draw)

    scaling = parsers["scaling"]
    scaling.description = (
        "From the more-systems cells of Lorenz-96 (n = 5 to 160) and the "
        "models their run cached, time every fitted estimator's estimate side by side "
        "(batch 20 and 1, one thread) and write scaling.md, scaling.csv and "
        "figures/scaling.png|svg with the fitted exponent of each cost. Run "
        "`kkl-bench run --track more-systems --estimator all` first, with the same --cache."
    )
    add_drawing_arguments(scaling, Path("leaderboard"), "the folder to write")
    add_cache_argument(scaling)
    scaling.add_argument(
        "--seed", type=seed, default=0, help="the training seed whose models are timed (default 0)"
    )
    timing = scaling.add_mutually_exclusive_group()
    timing.add_argument(
        "--missing-only",
        action="store_true",
        help="time only the fitted (estimator, n) that the study in --out has no online cost "
        "for, beside the EKF at the same sizes, and keep the other rows' costs (to add an "
        "estimator or a size without fitting the rest again)",
    )
    scaling.add_argument(
        "--untrained",
        action="store_true",
        help="time models built at the profile's sizes with their trainings cut short, in a "
        "temporary cache, given the published fits' choices made from data (an injection "
        "gain), instead of the trained models of --cache: the online cost is the "
        "structure's arithmetic, not the weights' values (protocol section 8); the study "
        "records which models each row's timing ran",
    )
    timing.add_argument(
        "--render-only",
        action="store_true",
        help="time nothing: rewrite the study in --out from the results and its stored "
        "online costs (rows never timed show '-'), e.g. after new cells or curves",
    )
    scaling.set_defaults(handler=scaling_study)

    throughput = parsers["throughput"]
    throughput.description = (
        "Run each learned row's fit at the profile's sizes from an empty "
        "temporary cache (nothing is kept), with every training measured instead of run "
        "to the end: one optimizer step's matrix products counted, then --steps steps "
        "timed, on --threads threads (or the GPU: --device), beside that device's float32 "
        "peak. Merges one row per training into DIR/training-throughput.csv and prints the "
        "table protocol 6.5 shows."
    )
    throughput.add_argument(
        "--estimator",
        nargs="+",
        metavar="NAME",
        help="estimators or variants to measure (default: every installed learned "
        "estimator; those that do not support a system are skipped there)",
    )
    throughput.add_argument(
        "--system",
        nargs="+",
        metavar="NAME",
        help="systems (default: the paper's four)",
    )
    throughput.add_argument("--profile", default="standard", help="profile (default standard)")
    throughput.add_argument(
        "--steps",
        type=positive_integer("steps"),
        default=20,
        help="optimizer steps timed per training (default 20)",
    )
    add_threads_argument(throughput, "measuring")
    throughput.add_argument(
        "--device",
        choices=DEVICES,
        default="cpu",
        help="where the trainings run while measured: cpu (default: where the board's fits "
        "train), cuda, or auto (cuda if torch sees a GPU); each row records it",
    )
    throughput.add_argument(
        "--render-only",
        action="store_true",
        help="measure nothing: print the table from DIR/training-throughput.csv",
    )
    add_out_argument(throughput, Path("leaderboard"), "the folder whose CSV to merge into")
    throughput.set_defaults(handler=measure_throughput)

    cost = parsers["cost"]
    cost.description = (
        "Load each estimator's trained models from the cache (fitting them if "
        "missing), then time its estimate on every test set of the chosen tracks, all "
        "estimators and the EKF beside them in turn in one process, on --threads threads, "
        "best of --rounds. Merges the rows into DIR/cost.csv (the other rows keep their own "
        "runs; --replace rewrites it), which `kkl-bench publish` shows in the cost table in "
        "place of the times the scoring runs measured (those come from many runs and "
        "machine loads)."
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
        "--seed", type=seed, default=0, help="the training seed whose models are timed (default 0)"
    )
    cost.add_argument(
        "--rounds", type=positive_integer("rounds"), default=3, help="timings per call (default 3)"
    )
    add_threads_argument(cost, "timing")
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
    add_out_argument(cost, Path("leaderboard"), "the folder whose cost.csv to merge into")
    add_cache_argument(cost)
    cost.set_defaults(handler=time_costs)


def publish_folder(args: argparse.Namespace) -> int:
    from kkl_bench.cli.common import exit_status, load
    from kkl_bench.report.publish import publish

    results, damaged = load(args)
    written = publish(results, args.results, args.out, args.margin, args.force)
    print(f"wrote {len(written)} files to {args.out}/")
    return exit_status(args, damaged)


def draw(args: argparse.Namespace) -> int:
    from kkl_bench.analysis.summary import summary_table
    from kkl_bench.cli.common import exit_status, load, of_track
    from kkl_bench.report.publish import draw_figures

    results, damaged = load(args)
    summary = summary_table(of_track(results, PAPER_TRACK))
    drawn = draw_figures(summary, args.results, args.profile, args.out)
    print(f"wrote {2 * len(drawn)} figures to {args.out / 'figures'}/")
    return exit_status(args, damaged)


def scaling_study(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import scaling, scaling_timing
    from kkl_bench.cli.common import exit_status, load
    from kkl_bench.report.scaling import write_study
    from kkl_bench.run import harness
    from kkl_bench.suite.task import get_profile

    results, damaged = load(args)
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
    commit = provenance()["git_commit"]  # the code that runs, read before anything is loaded
    study = args.out / "scaling.csv"
    stored = scaling_timing.stored_timings(study if args.missing_only or args.render_only else None)
    wanted = [] if args.render_only else scaling_timing.untimed(cells, stored)
    with tempfile.TemporaryDirectory() as untrained:  # kept until the models are timed
        fitted = {
            (estimator, n): (
                scaling_timing.fit_untrained(
                    replace(spec, cache_dir=Path(untrained)),
                    estimator,
                    n,
                    args.seed,
                    scaling_timing.published_report(results, estimator, n, args.seed),
                )
                if args.untrained
                else scaling_timing.fit_from_cache(spec, estimator, n, args.seed)
            )
            for estimator, n in tqdm(
                wanted,
                desc=f"{'building untrained' if args.untrained else 'loading fitted'} models",
                unit="model",
                disable=not wanted,
            )
        }
        if fitted:
            models = scaling.MODELS[1] if args.untrained else scaling.MODELS[0]
            timings = scaling_timing.time_estimators(spec, fitted)
            stored = scaling_timing.add_timings(
                stored, scaling_timing.timing_frame(timings, commit, models)
            )
    if not fitted and not args.render_only:
        print(f"every fitted estimator already has its online cost in {study}")
    curves = scaling.curve_frame(results, args.seed)
    written = write_study(cells, stored, profile, args.out, curves)
    print(f"wrote {', '.join(map(str, written))}")
    return exit_status(args, damaged)


def measure_throughput(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import throughput
    from kkl_bench.analysis.findings import PAPER_SYSTEMS
    from kkl_bench.cli.common import names
    from kkl_bench.suite.task import get_profile

    out = args.out / throughput.THROUGHPUT_FILE
    if not args.render_only:
        rows = throughput.measure(
            names(estimators, args.estimator) if args.estimator else throughput.learned(),
            names(systems, args.system or PAPER_SYSTEMS),
            get_profile(args.profile),
            out,
            args.steps,
            args.threads,
            args.device,
        )
        print(f"wrote {len(rows)} rows to {out}")
    stored = throughput.read_throughput(out)
    if stored is None:
        print(f"{out} does not exist: run kkl-bench throughput without --render-only first")
        return 1
    print(throughput.render(stored))
    return 0


def time_costs(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import cost, leaderboard
    from kkl_bench.cli.common import names
    from kkl_bench.report import markdown
    from kkl_bench.run import harness
    from kkl_bench.suite.task import get_profile

    spec = harness.RunSpec(
        estimators=names(estimators, args.estimator),
        systems=names(systems, args.system),
        regimes=None,
        tracks=tuple(args.track),
        profile=get_profile(args.profile),
        seeds=(args.seed,),
        cache_dir=args.cache or default_cache_dir(),
    )
    out = args.out / cost.COST_FILE
    rows = cost.measure(spec, out, args.rounds, args.threads, args.max_seconds, args.replace)
    print(markdown.table(leaderboard.measured_cost_table(rows)))
    kept = len(cost.read_costs(out)) - len(rows)
    print(
        f"wrote {len(rows)} rows (run {rows['run'].iloc[0]}) to {out}; "
        f"{kept} rows of earlier runs kept"
    )
    return 0
