"""``kkl-bench leaderboard``, ``kkl-bench compare`` and ``kkl-bench trainings``: tables of stored
results in the terminal.

Each handler imports the analysis it prints (pandas and the numerical stack), not the
module: ``--help`` and an argument error answer at once.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from kkl_bench.cli.arguments import add_reading_arguments
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.report.formats import FORMATS


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    board = parsers["leaderboard"]
    board.add_argument("--format", choices=FORMATS, default="markdown")
    add_reading_arguments(board)
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
    board.set_defaults(handler=print_leaderboard)

    versus = parsers["compare"]
    versus.description = (
        "Per cell: the ratio of A's mean RMSE to B's, its 90 % interval from the "
        "paired hierarchical bootstrap (test trajectories and seeds resampled) and the verdict "
        "of one-sided tests at 5 %."
    )
    versus.add_argument("a", metavar="A", help="estimator (or variant) name")
    versus.add_argument("b", metavar="B", help="estimator (or variant) name")
    add_reading_arguments(versus)
    versus.add_argument(
        "--track", default=PAPER_TRACK, metavar="NAME", help="the track (default: paper)"
    )
    versus.set_defaults(handler=compare)

    fits = parsers["trainings"]
    fits.description = (
        "Per learned row, system and training (read from the fit reports of the "
        "track's cells, each fit once): the fits, their steps, how many stopped at the "
        "plateau, at the cap or diverged (protocol 6.5), and the median step whose state was "
        "kept; then how many of the track's learned cells the board reads as converged. "
        "With --before, each row's mean RMSE per system (and regime, with --by-regime) "
        "against another results folder's, on the cells both scored (a refit's before and "
        "after); a cell with a diverged trajectory in either is left out of both means and "
        "counted; and what each row's fits spent in each (the median fit's steps and "
        "seconds, samples per second, and the clock its seconds were read on)."
    )
    add_reading_arguments(fits)
    fits.add_argument(
        "--track", default=PAPER_TRACK, metavar="NAME", help="the track (default: paper)"
    )
    fits.add_argument(
        "--before", type=Path, metavar="DIR", help="results to compare each row's RMSE with"
    )
    fits.add_argument(
        "--by-regime",
        action="store_true",
        help="with --before: compare per row, system and regime (default: per row and system)",
    )
    fits.set_defaults(handler=print_trainings)


def print_leaderboard(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import leaderboard
    from kkl_bench.analysis.summary import summary_table, track_summary, version_groups
    from kkl_bench.cli.common import exit_status, load, of_track
    from kkl_bench.report import markdown, text
    from kkl_bench.suite.task import get_profile, load_profiles
    from kkl_bench.suite.tracks import get_track

    results, damaged = load(args, check_versions=not args.by_version)
    if args.track == "summary":
        frame = track_summary(results)
        print(
            frame.to_csv(index=False, float_format="%.6g")
            if args.format == "csv"
            else markdown.table(leaderboard.track_summary_table(frame))
        )
        return exit_status(args, damaged)
    settling = get_track(args.track).settling
    results = of_track(results, args.track)
    with_paper = args.with_paper and args.track == PAPER_TRACK
    if args.format == "markdown":
        smoke = args.profile in load_profiles() and get_profile(args.profile).smoke
        print(leaderboard.caption(args.track, args.profile, smoke, settling))
    for label, cells in version_groups(results).items():
        if label:
            print(f"\n{label}\n" if args.format == "markdown" else f"# {label}")
        summary = summary_table(cells, with_paper=with_paper)
        print(text.render(summary, args.format, settling=settling), end="")
        if args.details:
            print("\n" + markdown.table(leaderboard.cost_table(summary)))
    return exit_status(args, damaged)


def compare(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import comparisons
    from kkl_bench.analysis.summary import summary_table
    from kkl_bench.cli.common import exit_status, load, of_track
    from kkl_bench.report import markdown

    results, damaged = load(args)
    results = of_track(results, args.track)
    print(markdown.table(comparisons.comparison_table(summary_table(results), args.a, args.b)))
    return exit_status(args, damaged)


def print_trainings(args: argparse.Namespace) -> int:
    from kkl_bench.analysis import trainings
    from kkl_bench.analysis.document import Table
    from kkl_bench.cli.common import exit_status, load, of_track
    from kkl_bench.report import markdown
    from kkl_bench.run.results import load_results

    results, damaged = load(args)
    results = of_track(results, args.track)
    records = trainings.training_records(results)
    if records.empty:
        raise ValueError(f"no trained fits among the {args.track} track's cells in {args.results}/")
    print(markdown.table(Table(trainings.training_table(records), intfmt=",")))
    said = [
        trainings.converged_sentence(trainings.cell_verdicts(results)),
        trainings.capped_sentence(records),
        trainings.diverged_sentence(records),
    ]
    print("\n" + "\n\n".join(sentence for sentence in said if sentence))
    if args.before is not None:
        before = of_track(load_results(args.before, profile=results["profile"].iloc[0]), args.track)
        change = trainings.rmse_change(before, results, by_regime=args.by_regime)
        print("\n" + markdown.table(Table(change, floatfmt=".4g")))
        costs = trainings.fit_cost_change(before, results)
        print(
            "\n"
            + trainings.FIT_COST_TEXT
            + "\n\n"
            + markdown.table(Table(costs, floatfmt=",.0f", intfmt=","))
        )
    elif args.by_regime:
        raise ValueError("--by-regime compares with --before DIR; name the folder to compare with")
    return exit_status(args, damaged)
