"""``kkl-bench verify``: re-derive published cells and say whether their numbers stand."""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

from kkl_bench.cli.arguments import (
    PUBLISHED_RESULTS,
    add_jobs_argument,
    add_out_argument,
    add_results_argument,
    positive_integer,
    seed,
)
from kkl_bench.cli.run import advance, duration_text, showing_jobs, work_bar
from kkl_bench.run import verification
from kkl_bench.run.results import read_cell
from kkl_bench.support.provenance import provenance


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    verify = parsers["verify"]
    verify.description = (
        "Recompute cells (named ones, or a random sample) at the current commit "
        "from an empty model cache, exactly as `kkl-bench run` made them, and report per "
        "cell: identical (bit for bit), within tolerance (largest per-trajectory relative "
        "RMSE difference) or drifted, with the likely cause. Each verdict is appended to "
        f"--out/{verification.VERIFICATION_FILE} as soon as it is known; `kkl-bench publish` "
        "reports the latest run in the board's Reproduce section. Exit 1 if any cell drifted."
    )
    verify.add_argument(
        "cells",
        nargs="*",
        metavar="CELL",
        help="cell records by their path under RESULTS/PROFILE, with or without .json "
        "(ekf/duffing/sinusoid-seed0, ukf/vdp/hard/outliers-sinusoid-seed0)",
    )
    verify.add_argument(
        "--sample",
        type=positive_integer("--sample"),
        metavar="N",
        help="verify N cells drawn at random from every cell of the profile",
    )
    verify.add_argument(
        "--sample-seed",
        type=seed,
        help="the draw of --sample (default: a fresh one, recorded with the verdicts so that "
        "the same cells can be drawn again)",
    )
    add_results_argument(verify, PUBLISHED_RESULTS)
    verify.add_argument(
        "--profile", default="standard", help="the profile of the cells (default standard)"
    )
    add_out_argument(verify, Path("leaderboard"), f"where {verification.VERIFICATION_FILE} goes")
    verify.add_argument(
        "--tolerance",
        type=float,
        default=verification.TOLERANCE,
        help="largest relative difference of a trajectory's RMSE still 'within tolerance' "
        f"(default {verification.TOLERANCE:g})",
    )
    add_jobs_argument(verify, "cell recomputations")
    verify.add_argument(
        "--replace-drifted",
        action="store_true",
        help="replace each drifted cell's record (and kept estimate) in --results by the "
        "recomputed one (default: report only)",
    )
    verify.add_argument(
        "--resume",
        action="store_true",
        help="go on with the latest run, interrupted: same cells (or the same --sample and "
        "--sample-seed); the cells it has verdicts for are not recomputed and the new "
        "verdicts join that run, each with the commit that verified it",
    )
    verify.set_defaults(handler=verify_cells)


def verify_cells(args: argparse.Namespace) -> int:
    if (args.sample is None) == (not args.cells):
        raise ValueError("name the cells to verify or give --sample N (one of the two)")
    if not args.tolerance >= 0:
        raise ValueError(f"--tolerance must be a non-negative number, got {args.tolerance!r}")
    if args.cells:
        paths = verification.named_cells(args.results, args.profile, args.cells)
        selection = "named"
    else:
        every = verification.cell_files(args.results, args.profile)
        if not every:
            raise ValueError(f"no cells of profile {args.profile!r} under {args.results}/")
        draw = (
            random.SystemRandom().randrange(2**31) if args.sample_seed is None else args.sample_seed
        )
        paths = verification.sampled_cells(every, args.sample, draw)
        selection = f"random {len(paths)} of {len(every)} (--sample-seed {draw})"
    commit = provenance()["git_commit"]
    out_file = args.out / verification.VERIFICATION_FILE
    root = args.results / args.profile
    run = None
    if args.resume:
        run, done = verification.run_to_resume(out_file, selection)
        paths = [path for path in paths if path.relative_to(root).as_posix() not in done]
        print(
            f"going on with the run of {run}: {len(done)} cell(s) verified before",
            file=sys.stderr,
        )
    estimates = dict(
        zip(
            (path.relative_to(root).as_posix() for path in paths),
            verification.estimated_seconds([read_cell(path) for path in paths]),
            strict=True,
        )
    )
    print(
        f"verifying {len(paths)} cell(s) at commit {commit}, {selection}; estimated "
        f"{duration_text(sum(estimates.values()))} on one thread a cell (from the cells' recorded "
        "training and scoring times, each model trained once)",
        file=sys.stderr,
    )
    with (
        tempfile.TemporaryDirectory(prefix="kkl-bench-verify-") as work,
        work_bar(sum(estimates.values()), f"verify ({len(paths)} cells, estimated work)") as bar,
        showing_jobs(bar, Path(work) / "results" / ".claims" / args.profile),
    ):

        def report(row: dict) -> None:
            difference = row["largest_relative_difference"]
            tqdm.write(
                f"{row['verdict']:>16}  {row['cell']}"
                + (f"  (largest difference {difference:.3g}" if difference else "")
                + (f"; {row['cause']})" if row["cause"] else (")" if difference else ""))
            )
            advance(bar, estimates[row["cell"]])

        rows = verification.verify(
            paths,
            args.results,
            out_file,
            selection,
            Path(work),
            args.tolerance,
            args.replace_drifted,
            args.command_line,
            on_cell=report,
            jobs=args.jobs,
            run=run,
        )
    counts = rows["verdict"].value_counts()
    print(
        ", ".join(f"{counts.get(v, 0)} {v}" for v in verification.VERDICTS)
        + f"; verdicts appended to {out_file}"
    )
    return 1 if counts.get(verification.DRIFTED, 0) else 0
