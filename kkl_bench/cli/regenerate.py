"""``kkl-bench regenerate``: compute a published board's cells again, resumably, with
its plan and estimated core-hours said first and an ETA counted in work.

The handler imports the planner and the harness, not the module: ``--help`` and an
argument error answer at once.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from kkl_bench.cli.arguments import PUBLISHED_RESULTS, add_cache_argument, add_jobs_argument
from kkl_bench.cli.run import RESUME, following, showing_jobs, work_bar
from kkl_bench.run import ledger
from kkl_bench.support.cache import default_cache_dir
from kkl_bench.support.device_names import DEVICES
from kkl_bench.support.executors import EXECUTORS
from kkl_bench.support.provenance import is_clean_commit, provenance


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    parser = parsers["regenerate"]
    parser.description = (
        "Plan the jobs that make every cell of --from (one profile; narrowed by "
        "--estimator, --track, --system): fits, and jobs that only score trained models. "
        "Print the plan and its estimated core-hours, then compute the cells into --into, "
        "each row as `kkl-bench run` of that row makes it. Rerun the same command to resume: "
        "finished cells are skipped and a killed training continues from its checkpoint. "
        f"Each job's processor time goes to --into/"
        f"{ledger.LEDGER_FILE}; `kkl-bench publish --results INTO` states the core-hours."
    )
    parser.add_argument(
        "--from",
        dest="source",
        type=Path,
        default=PUBLISHED_RESULTS,
        metavar="DIR",
        help="the results whose cells are regenerated (default leaderboard/results); never written",
    )
    parser.add_argument(
        "--into", type=Path, required=True, metavar="DIR", help="where the new cells go"
    )
    parser.add_argument("--profile", default="standard", help="profile (default standard)")
    parser.add_argument("--estimator", nargs="+", metavar="ROW", help="rows (default: all)")
    parser.add_argument("--track", nargs="+", metavar="NAME", help="tracks (default: all)")
    parser.add_argument("--system", nargs="+", metavar="NAME", help="systems (default: all)")
    parser.add_argument(
        "--redo",
        nargs="+",
        metavar="ROW",
        help="after a committed change of these rows' training: make their cells of the "
        "selection again where --into holds them from another commit (their ledger jobs are "
        "kept apart, with --because); cells made at this commit stay, so it resumes too",
    )
    parser.add_argument(
        "--capped-only",
        action="store_true",
        help="with --redo: only the cells whose fit reached a cap of steps (after a cap was "
        "raised; the fits the plateau rule stopped would come back bit for bit)",
    )
    parser.add_argument(
        "--because",
        metavar="TEXT",
        help="with --redo (required): why the cells are made again, which the board states",
    )
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="print the plan and its estimate (with what --redo would remove among it), change "
        "nothing",
    )
    add_cache_argument(parser)
    add_jobs_argument(
        parser, "jobs (fits, or scoring only; two that need one model not trained yet never)"
    )
    parser.add_argument(
        "--device",
        choices=DEVICES,
        default="cpu",
        help="where torch estimators train: cpu (default: where the board's fits train, "
        "and what its core-hours count), cuda or auto; each job's device goes to the ledger",
    )
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="loky",
        help="loky: local worker processes (default); dask: a Dask cluster (see --scheduler)",
    )
    parser.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address")
    parser.set_defaults(handler=regenerate_command)


def regenerate_command(args: argparse.Namespace) -> int:
    from kkl_bench.cli.common import device_before_work
    from kkl_bench.run import regenerate
    from kkl_bench.run.results import load_results
    from kkl_bench.suite.task import get_profile

    if args.into.resolve() == args.source.resolve():
        raise ValueError(
            f"--into {args.into} is the source folder: regenerate into another folder, then "
            "publish from it"
        )
    if bool(args.redo) != bool(args.because):
        raise ValueError("--redo ROW... and --because TEXT go together: name the rows and why")
    if args.capped_only and not args.redo:
        raise ValueError("--capped-only narrows --redo ROW...: name the rows to make again")
    profile = get_profile(args.profile)
    device_before_work(args)
    source = regenerate.select(load_results(args.source), args.estimator, args.track, args.system)
    if source.empty:
        raise ValueError(f"{args.source} holds no cells of the selection")
    redone = None
    if args.redo:
        redone = regenerate.redo(
            source,
            profile,
            args.into,
            args.redo,
            args.because,
            dry_run=args.dry_run,
            capped_only=args.capped_only,
        )
        print(redone.describe())
    commit = provenance()["git_commit"]
    if not is_clean_commit(commit):
        print(
            f"kkl-bench: the code is not a clean commit ({commit}): a regenerated board "
            "should come from one",
            file=sys.stderr,
        )
    planned = regenerate.plan(
        source,
        profile,
        args.into,
        args.cache or default_cache_dir(),
        args.command_line,
        args.device,
        recompute=redone.cells if redone and redone.dry_run else (),
    )
    print(planned.describe())
    if args.dry_run or not planned.jobs:
        return 0
    failed = 0
    done = regenerate.WorkDone(planned, args.into, time.time_ns())
    spent, total = done.measure()
    with (
        work_bar(total, "regenerate (processor time)", spent) as bar,
        showing_jobs(bar, args.into / ".claims" / profile.name),
        following(bar, done.measure, ledger.METER_EVERY_S) as update,
    ):

        def progress(planned_job, outcome):
            nonlocal failed
            failed += sum(cell.status == "error" for cell in outcome.scored)
            done.finish(planned_job)
            update()

        try:
            written = regenerate.run(
                planned, args.into, progress, args.jobs, args.executor, args.scheduler
            )
        except KeyboardInterrupt:
            print(f"kkl-bench: interrupted; {RESUME}", file=sys.stderr)
            return 130
    summary = ledger.ledger_summary(written)
    print(
        f"{summary['cells']} cells in {summary['jobs']} jobs, {summary['core_hours']:.2f} "
        f"core-hours measured (estimated {summary['estimated_core_hours']:.2f}); {failed} "
        f"failed cells; results in {args.into}/{profile.name}/" + (f"; {RESUME}" if failed else "")
    )
    return 1 if failed else 0
