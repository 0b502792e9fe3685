"""``kkl-bench run``: fit estimators and score them, with a progress line of what each job does.

The machinery of a run (the harness, the tasks, torch) is imported when the command runs,
not with the module: ``kkl-bench run --help`` and an argument error answer at once.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import statistics
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from kkl_bench.cli.arguments import (
    add_cache_argument,
    add_jobs_argument,
    add_results_argument,
    positive_integer,
    seed,
)
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import estimators, systems
from kkl_bench.support import status
from kkl_bench.support.cache import default_cache_dir
from kkl_bench.support.device_names import DEVICES
from kkl_bench.support.executors import EXECUTORS
from kkl_bench.support.provenance import is_clean_commit, provenance

if TYPE_CHECKING:
    from kkl_bench.run import harness

DEFAULT_PROFILE = "quick"

RESUME = (
    "every finished cell is saved; run the same command again to resume (finished cells "
    "are skipped, failed and missing ones computed)"
)


def add_arguments(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Declare the arguments and the handler of each command of this module (``parsers``:
    their parsers by name, :data:`kkl_bench.cli.COMMANDS`)."""
    run = parsers["run"]
    run.description = (
        "Fit each estimator once per system, score it on every regime's test set, "
        "and write one result file per cell. Cells already on disk are skipped (use --force)."
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
    run.add_argument("--profile", default=None, help="profile: quick (the default) or standard")
    run.add_argument(
        "--seed",
        type=seed,
        nargs="+",
        default=[0],
        metavar="SEED",
        help="training seeds, one fit per seed (default 0); estimators that ignore "
        "the seed (the filters) run with the first only",
    )
    add_results_argument(run)
    add_cache_argument(run)
    add_jobs_argument(run, "(estimator, system) jobs")
    run.add_argument(
        "--threads",
        type=positive_integer("threads"),
        default=None,
        metavar="N",
        help="torch and BLAS threads per job (default 1: two runs side by side, or --jobs "
        "up to the cores, never oversubscribe them; at most the cores over --jobs)",
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
    run.add_argument(
        "--own-rows-only",
        action="store_true",
        help="fit each estimator for its own row only, not its +logged or +truth rows (to "
        "score its cells again after its fit changed)",
    )
    run.set_defaults(handler=run_command)


def run_command(args: argparse.Namespace) -> int:
    from kkl_bench.cli.common import device_before_work, names
    from kkl_bench.run import harness
    from kkl_bench.suite.task import get_profile
    from kkl_bench.suite.tracks import load_tracks

    spec = harness.RunSpec(
        estimators=names(estimators, args.estimator),
        systems=names(systems, args.system),
        regimes=tuple(dict.fromkeys(args.regime)) if args.regime else None,
        tracks=tuple(load_tracks()) if args.track == ["all"] else tuple(args.track),
        profile=get_profile(args.profile or DEFAULT_PROFILE),
        seeds=tuple(args.seed),
        results_dir=args.results,
        cache_dir=args.cache or default_cache_dir(),
        force=args.force,
        device=args.device,
        command=args.command_line,
        own_rows_only=args.own_rows_only,
    )
    args.profile_given = args.profile is not None
    device = device_before_work(args)
    commit = provenance()["git_commit"]
    if commit is not None and not is_clean_commit(commit):
        print(
            f"kkl-bench: the code has uncommitted changes ({commit}): the cells and any model "
            "trained now record a commit that does not hold the code that made them",
            file=sys.stderr,
        )
    todo, done = harness.plan(spec)
    weights = announce(spec, todo, len(done), args.profile_given, device)
    per_cell = {  # a fit's estimated seconds, shared out over the cells it scores
        (job.estimator, task.id, job.seed): weight / len(job.tasks)
        for job, weight in zip(todo, weights, strict=True)
        for task in job.tasks
    }
    with (
        work_bar(sum(weights), f"kkl-bench ({len(todo)} fits, estimated work)") as bar,
        showing_jobs(bar, spec.results_dir / ".claims" / spec.profile.name),
    ):

        def progress(cell, outcome):
            if outcome == "error":
                tqdm.write(f"error in {cell.estimator} {cell.task}: {cell.error.splitlines()[-1]}")
            advance(bar, per_cell.get((cell.estimator, cell.task, cell.seed), 0.0))

        try:
            summary = harness.run(
                spec,
                progress,
                jobs=args.jobs,
                executor=args.executor,
                scheduler=args.scheduler,
                threads=args.threads,
                planned=(todo, done),
            )
        except KeyboardInterrupt:
            print(f"kkl-bench: interrupted; {RESUME}", file=sys.stderr)
            return 130
    print(
        f"{len(summary.scored)} cells scored, {len(summary.cached)} already done, "
        + (f"{len(summary.unsupported)} unsupported, " if summary.unsupported else "")
        + f"{len(summary.failed)} failed; results in {spec.results_dir}/{spec.profile.name}/"
        + (f"; {RESUME}" if summary.failed else "")
    )
    return 0 if summary.ok else 1


BAR = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]"
"""The progress bar of a run: the share of the estimated work done and the time left."""


def work_bar(total_s: float, desc: str, done_s: float = 0.0) -> tqdm:
    """A bar over ``total_s`` seconds of estimated work, ``done_s`` of it already done
    (a resumed plan's banked work); its time left is read from the average rate since it
    started, so a burst of quick cells does not set it."""
    return tqdm(
        total=total_s,
        initial=done_s,
        unit="s",
        desc=desc,
        dynamic_ncols=True,
        mininterval=1.0,
        smoothing=0.0,
        bar_format=BAR,
    )


@contextlib.contextmanager
def following(
    bar: tqdm, measure: Callable[[], tuple[float, float]], every_s: float
) -> Iterator[Callable[[], None]]:
    """Set ``bar``'s position and total to ``measure()`` (seconds of work done, and in
    all, at least the work done) every ``every_s`` seconds while the block runs, for
    work whose progress is measured rather than counted and whose total grows where a
    job takes longer than expected; yields the function that does it at once (after a
    job ends)."""
    lock, stop = threading.Lock(), threading.Event()

    def update() -> None:
        with lock:
            bar.n, bar.total = measure()
            bar.refresh()

    def follow() -> None:
        while not stop.wait(every_s):
            update()

    thread = threading.Thread(target=follow, daemon=True)
    thread.start()
    try:
        yield update
    finally:
        stop.set()
        thread.join()


def advance(bar: tqdm, seconds: float) -> None:
    """Move ``bar`` on by ``seconds`` of estimated work, never past its total: the shares
    of the estimate that the jobs report, summed in another order than the total was, can
    exceed it by a rounding error, which tqdm answers with a warning and a negative time
    left."""
    bar.update(min(seconds, bar.total - bar.n))


def announce(
    spec: harness.RunSpec, todo, done: int, profile_given: bool, device: str | None = "cpu"
) -> list[float]:
    """Print the run's plan (profile, fits, cells, and ``device`` where torch estimators
    train, if not the CPU; None: each Dask worker's ``auto``) and its estimated duration,
    before any work; returns each fit's estimated seconds (the median of the others, or 1,
    where none is recorded: the bar still advances by fits)."""
    from kkl_bench.run import fit_times

    cells = sum(len(job.tasks) for job in todo)
    rows = ", ".join(dict.fromkeys(job.estimator for job in todo)) or "nothing"
    profile = spec.profile.name + ("" if profile_given else " (the default; --profile to choose)")
    table = fit_times.known(spec.results_dir, spec.profile.name)
    seconds, unknown = fit_times.estimate(
        [(job.estimator, job.system, len(job.tasks)) for job in todo], spec.profile.name, table
    )
    recorded = [s for s in seconds if not math.isnan(s)]
    if not todo:
        duration = "nothing to do"
    elif not unknown:
        duration = f"estimated {duration_text(sum(recorded))} (fit times recorded on this profile)"
    else:
        duration = (
            f"estimated {duration_text(sum(recorded))} for the fits recorded on this profile; "
            f"no estimate for {', '.join(unknown[:4])}{' ...' if len(unknown) > 4 else ''} "
            "(none recorded): the time left shows after the first"
        )
    where = {"cpu": "", None: "; torch estimators train on each worker's device (auto)"}.get(
        device, f"; torch estimators train on {device}"
    )
    print(
        f"kkl-bench run: profile {profile}; {len(todo)} fits of {rows} making {cells} cells "
        f"({done} already done){where}; {duration}",
        file=sys.stderr,
    )
    fallback = statistics.median(recorded) if recorded else 1.0
    return [fallback if math.isnan(s) else s for s in seconds]


def duration_text(seconds: float) -> str:
    """``seconds`` as ``42 s``, ``12 min`` or ``3.5 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


@contextlib.contextmanager
def showing_jobs(bar: tqdm, claims: Path, every_s: float = 1.0) -> Iterator[None]:
    """Show beside ``bar``, every ``every_s`` seconds, what each running job says it does
    (:mod:`kkl_bench.support.status`): which estimator fits or scores on which system, and how
    far its training is."""
    since, stop = time.time() - 1.0, threading.Event()

    def show() -> None:
        while not stop.wait(every_s):
            bar.set_postfix_str(" | ".join(status.current(claims, since)) or "")

    thread = threading.Thread(target=show, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        bar.set_postfix_str("")
