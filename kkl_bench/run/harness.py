"""Runs estimators over the benchmark grid and records every cell as it finishes.

For each (estimator, system, seed) the harness builds the estimator, fits it
once with a :class:`~kkl_bench.estimator.FitContext` (the paper's noise, x0
box and horizon, whatever the tracks), then scores it on the test sets of
every requested track's tasks: tracks test generalization, never retraining.
Each cell is written atomically the moment it
is scored, with the truth and the estimate of its first test trajectory
beside it; a cell already on disk is skipped unless ``force`` is set.
Estimators that do not depend on the seed run with the first seed only. On
a track whose plant differs from the nominal model (``mismatch``), an
estimator that declares ``uses_logged_data`` is also fitted once per true
plant with the data logged on it, and scored on that plant's tasks as the
row ``<name>+logged``. On a track fitted per task (``hard``), every
estimator is fitted once per measurement model instead, under its own name;
an estimator that declares ``bayes_limit`` is also fitted with the truth of
the generalization tracks' tasks, as ``<name>+truth``. These are the only
exceptions to fitting once. An estimator that cannot handle a task's
measurement model gets ``unsupported`` cells with its reason and no fit. An
estimator that raises, or returns the wrong shape, produces an ``error``
cell and the run goes on.
"""

from __future__ import annotations

import time
import traceback
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

from kkl_bench import families, variants
from kkl_bench.protocol import PROTOCOL_ID
from kkl_bench.registry import estimators
from kkl_bench.run.results import (
    CellResult,
    DamagedCellError,
    cell_path,
    check_writable,
    claim,
    claim_path,
    move_aside,
    read_cell,
    write_cell,
)
from kkl_bench.run.scoring import score
from kkl_bench.run.spec import RunSpec, fit_context_for_row, fit_groups, truth_groups
from kkl_bench.suite.task import Task, make_test_set, stream_fingerprint
from kkl_bench.suite.tracks import Plant
from kkl_bench.support import status
from kkl_bench.support.executors import execute
from kkl_bench.support.provenance import provenance


@dataclass
class RunSummary:
    """Counts of what a run did, by cell status."""

    scored: list[CellResult] = field(default_factory=list)
    cached: list[CellResult] = field(default_factory=list)
    failed: list[CellResult] = field(default_factory=list)
    unsupported: list[CellResult] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failed


def _cell(spec: RunSpec, name: str, params: dict, task: Task, seed: int, **fields) -> CellResult:
    """The record of ``task``'s cell for estimator ``name`` (hyperparameters ``params``)."""
    test_set = make_test_set(task, spec.profile.n_test)
    return CellResult(
        estimator=name,
        family=families.row_family(name),
        system=task.system,
        regime=task.regime,
        task=task.id,
        track=task.track,
        profile=spec.profile.name,
        seed=seed,
        n_test=spec.profile.n_test,
        estimator_params=params,
        protocol=PROTOCOL_ID,
        test_set_fingerprint=test_set.fingerprint,
        stream_fingerprint=test_set.stream_fingerprint,
        provenance={**provenance(), "command": spec.command},
        **fields,
    )


def _error_text(error: BaseException) -> str:
    return "".join(traceback.format_exception(error)).strip()


def _unscored(
    spec: RunSpec, row: str, estimator, tasks: list[Task], seed: int, outcome: str, error: str
) -> Iterator[CellResult]:
    """A cell of status ``outcome`` with ``error`` for each task, written, then yielded: what
    a job records when its estimator is not fitted (unsupported) or its fit failed."""
    for task in tasks:
        cell = _cell(spec, row, estimator.get_params(), task, seed, status=outcome, error=error)
        write_cell(spec.results_dir, cell)
        yield cell


def run_system(
    spec: RunSpec, estimator_name: str, system: str, tasks: Iterable[Task], seed: int
) -> Iterator[CellResult]:
    """Fit ``estimator_name`` (a row name: an estimator, a variant, ``<name>+logged`` or
    ``<name>+truth``) on ``system`` with ``seed`` once and score it on each task, yielding
    cells.

    Each cell is written to ``spec.results_dir`` before it is yielded.
    """
    estimator = variants.build(variants.split_row(estimator_name)[0])
    tasks = list(tasks)
    context = fit_context_for_row(spec, estimator_name, system, tasks, seed)
    reason = estimator.unsupported_reason(context.system, context.measurement)
    if reason is not None:
        yield from _unscored(spec, estimator_name, estimator, tasks, seed, "unsupported", reason)
        return
    start = time.perf_counter()
    status.say("fitting")
    try:
        estimator.fit(context)
    except Exception as error:
        error_text = f"fit failed: {_error_text(error)}"
        yield from _unscored(spec, estimator_name, estimator, tasks, seed, "error", error_text)
        return
    fit_time = time.perf_counter() - start
    report = estimator.fit_report()
    for number, task in enumerate(tasks, 1):
        status.say(f"scoring {task.track}/{task.regime} ({number}/{len(tasks)})")
        kept = None
        try:
            metrics, kept = score(estimator, make_test_set(task, spec.profile.n_test))
            fields = {"status": "ok", **metrics}
        except Exception as error:
            fields = {"status": "error", "error": f"estimate failed: {_error_text(error)}"}
        cell = _cell(
            spec,
            estimator_name,
            estimator.get_params(),
            task,
            seed,
            fit_time_s=fit_time,
            fit_report=report,
            **fields,
        )
        write_cell(spec.results_dir, cell, kept)
        yield cell


@dataclass(frozen=True)
class Job:
    """One unit of work: fit ``estimator`` on ``system`` with ``seed`` once, score it on ``tasks``.

    ``estimator`` is a result row's name: ``<name>+logged`` fits with the logged data of
    the one plant its tasks share.
    """

    estimator: str
    system: str
    tasks: tuple[Task, ...]
    seed: int = 0


@dataclass
class JobOutcome:
    """The cells of a job: those it scored and those another run had finished meanwhile."""

    job: Job
    scored: list[CellResult]
    done_elsewhere: list[CellResult]


def run_job(spec: RunSpec, job: Job) -> JobOutcome:
    """Run ``job`` (each cell is written as it finishes).

    The job is claimed first (a file lock in the results directory, see
    :func:`kkl_bench.run.results.claim`): a concurrent run on the same results
    waits, then scores only the cells still missing.
    """
    provenance()  # the code's commit now, before a long fit: the checkout may move on meanwhile
    lock = claim_path(spec.results_dir, job.estimator, job.system, spec.profile.name, job.seed)
    with (
        claim(spec.results_dir, job.estimator, job.system, spec.profile.name, job.seed),
        status.reporting(
            status.status_path(lock.parent, lock.stem),
            f"{job.estimator} on {job.system}, seed {job.seed}",
        ),
    ):
        done = {task: _done(spec, job.estimator, task, job.seed) for task in job.tasks}
        todo = [task for task, cell in done.items() if cell is None]
        scored = list(run_system(spec, job.estimator, job.system, todo, job.seed)) if todo else []
    return JobOutcome(job, scored, [cell for cell in done.values() if cell is not None])


def _done(spec: RunSpec, estimator: str, task: Task, seed: int) -> CellResult | None:
    """The finished cell on disk, or None if it is to be (re)computed.

    A damaged cell file is moved aside (``<name>.corrupt``) with a warning
    naming it and the reason, and the cell is recomputed. So is, with a
    warning, a cell whose random draws differ from the task's today (its track
    file's noise, box, horizon or family was edited without a new version;
    the stream fingerprint cannot see a changed parameter range, which is
    what the track's version is for).
    """
    path = cell_path(
        spec.results_dir, estimator, task.system, task.regime, spec.profile.name, seed, task.track
    )
    if spec.force or path in spec.recompute or not path.exists():
        return None
    try:
        cell = read_cell(path)
    except DamagedCellError as error:
        aside = move_aside(path)
        warnings.warn(f"{error}; moved to {aside.name}, recomputing the cell", stacklevel=2)
        return None
    # errors are retried; unsupported cells are decided anew unless the spec keeps them
    if cell.status != "ok" and not (spec.keep_unsupported and cell.status == "unsupported"):
        return None
    if cell.stream_fingerprint != stream_fingerprint(task, cell.n_test):
        warnings.warn(
            f"{path} was scored on other test trajectories than {task.id} draws now (was its "
            "track file edited without a new version?); recomputing the cell",
            stacklevel=2,
        )
        return None
    return cell


def plan(spec: RunSpec) -> tuple[list[Job], list[CellResult]]:
    """The jobs still to run and the cells already done (skipped unless ``spec.force``).

    Jobs come estimator by estimator, each over its seeds and systems: the
    first KKL estimator trains every Phase-1 model, so parallel workers train
    different models instead of waiting for one another's claim.
    """
    jobs, cached = [], []
    for estimator in spec.estimators:
        for seed in spec.seeds_for(estimator):
            for system in spec.systems:
                for row, tasks in rows_and_tasks(spec, estimator, system):
                    todo = []
                    for task in tasks:
                        done = _done(spec, row, task, seed)
                        if done is None:
                            todo.append(task)
                        else:
                            cached.append(done)
                    if todo:
                        jobs.append(Job(row, system, tuple(todo), seed))
    return jobs, cached


def rows_and_tasks(spec: RunSpec, estimator: str, system: str) -> list[tuple[str, list[Task]]]:
    """The fits ``estimator`` makes on ``system``: each result row with the tasks of one fit.

    Its own row on every selected task, one fit per group of :func:`~kkl_bench.run.spec.fit_groups`
    (one for all tasks but those of a track fitted per task); if it uses logged data,
    ``<name>+logged`` on the tasks of each true plant (one fit per plant); if it is a Bayes
    limit, ``<name>+truth`` on the tasks whose truth differs from the protocol's (one fit
    per truth); neither with ``spec.own_rows_only``. ``estimator`` may name one of those
    rows (``particle_filter+truth``): its fits only.
    """
    tasks = spec.tasks(system)
    name, only = variants.split_row(estimator)
    declared = estimators.get(variants.base_name(name))
    if only and not (declared.bayes_limit if only == variants.TRUTH else declared.uses_logged_data):
        kind = "a Bayes limit" if only == variants.TRUTH else "an estimator that uses logged data"
        raise ValueError(f"row {estimator!r}: {name!r} is not {kind}, so it has no {only} row")
    rows = [(name, group) for _, group in fit_groups(tasks)]
    if spec.own_rows_only:
        return rows
    if declared.bayes_limit:
        rows += [(variants.truth_row(name), group) for _, group in truth_groups(tasks)]
    if declared.uses_logged_data:
        by_plant: dict[tuple[str, Plant], list[Task]] = {}
        for task in tasks:
            plant = task.definition.plant
            if not plant.nominal:
                by_plant.setdefault((task.track, plant), []).append(task)
        rows += [(variants.logged_row(name), group) for group in by_plant.values()]
    # ``<name>+truth`` or ``<name>+logged`` asked for: that row's fits only
    return [(row, group) for row, group in rows if not only or row == estimator]


def _lost_cells(spec: RunSpec, job: Job, error: BaseException) -> list[CellResult]:
    """Cells of ``job`` after its worker died: those it wrote, the rest as errors (written)."""
    cells = []
    for task in job.tasks:
        done = _done(spec, job.estimator, task, job.seed)
        if done is None:
            done = _cell(
                spec,
                job.estimator,
                {},
                task,
                job.seed,
                status="error",
                error=f"not completed: the run stopped ({type(error).__name__}: {error})",
            )
            write_cell(spec.results_dir, done)
        cells.append(done)
    return cells


def run(
    spec: RunSpec,
    progress: Callable[[CellResult, str], None] | None = None,
    jobs: int = 1,
    executor: str = "loky",
    scheduler: str | None = None,
    threads: int | None = None,
    planned: tuple[list[Job], list[CellResult]] | None = None,
) -> RunSummary:
    """Run the grid of ``spec``; ``progress(cell, status)`` is called for every cell.

    ``status`` is ``"cached"`` (already on disk, skipped), ``"ok"``,
    ``"diverged"`` (scored, some trajectory diverged), ``"unsupported"`` (the estimator
    cannot be fitted for the task: :meth:`~kkl_bench.estimator.Estimator.unsupported_reason`)
    or ``"error"``. Jobs (estimator x system) run through
    :func:`kkl_bench.support.executors.execute` with ``jobs``, ``executor``, ``scheduler`` and
    ``threads`` (per job; default one).
    If a worker dies, every finished cell is kept, the others are recorded as errors,
    and the run returns. ``planned`` is :func:`plan` of ``spec`` if the caller made it
    already (to announce the run); each job rechecks its cells under its claim anyway.
    """
    check_writable(spec.results_dir)
    summary = RunSummary()
    report = progress or (lambda cell, status: None)
    todo, cached = planned if planned is not None else plan(spec)
    for cell in cached:
        summary.cached.append(cell)
        report(cell, "cached")

    def record(cell: CellResult) -> None:
        if cell.status == "ok":
            summary.scored.append(cell)
            report(cell, "diverged" if cell.n_diverged else "ok")
        elif cell.status == "unsupported":
            summary.unsupported.append(cell)
            report(cell, "unsupported")
        else:
            summary.failed.append(cell)
            report(cell, "error")

    returned = set()
    try:
        arguments = [(spec, job) for job in todo]
        for outcome in execute(run_job, arguments, jobs, executor, scheduler, threads):
            returned.add(outcome.job)
            for cell in outcome.done_elsewhere:
                summary.cached.append(cell)
                report(cell, "cached")
            for cell in outcome.scored:
                record(cell)
    except (KeyboardInterrupt, ValueError):
        raise
    except Exception as error:  # a worker died (killed, out of memory): keep what finished
        for job in todo:
            if job not in returned:
                for cell in _lost_cells(spec, job, error):
                    record(cell)
    return summary
