"""Regenerate published cells with one resumable command (``kkl-bench regenerate``).

The plan is read from a results folder (the published ``leaderboard/results``): every
cell of one profile, optionally narrowed to some rows, tracks and systems, is computed
again into another folder by the harness's own jobs (:class:`~kkl_bench.run.harness.Job`:
one fit, the cells it scores), with each row run as a ``kkl-bench run`` of that row
would run it. Nothing in the source folder is written. A job's cost is estimated from
the source cells' own records (the training seconds stored with their models, the
Phase-1 models the KKL rows share counted once, and their scoring time), so the plan
states its core-hours before it starts, and the progress bar counts processor seconds
of work (:class:`WorkDone`), not cells. A job is a fit (it trains a model) or scores
only (its models are trained by an earlier job, or already, for cells of other
tracks). A resumed regeneration also says how many times their estimates the jobs it
finished took, and counts the training of each row's remaining jobs at its row's rate
on the job's track where one of its jobs there finished, else at its row's
(:func:`measured_rates`).

The run is resumable like ``kkl-bench run``: cells already in the target folder are
skipped, and a killed training continues from its checkpoint in the model cache. Each
job's measured processor time (one thread per job: its core-seconds), with what its
killed attempts had spent (their meters, :func:`~kkl_bench.run.ledger.metered`), is
added to the target folder's :data:`~kkl_bench.run.ledger.LEDGER_FILE` when it ends, so
the core-hours of a regeneration spread over several invocations, or machines, add up;
the board's Reproduce section reads them.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from kkl_bench import variants
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.run import harness
from kkl_bench.run.harness import Job, JobOutcome, RunSpec
from kkl_bench.run.ledger import (
    LEDGER_FILE,
    interrupted_times,
    key_parts,
    killed_attempts,
    metered,
    read_ledger,
    record_job,
    running_seconds,
    supersede,
)
from kkl_bench.run.results import (
    cell_path,
    estimate_path,
    phase_seconds,
    read_cell,
    scoring_seconds,
    trained_models,
)
from kkl_bench.suite.task import Profile, Task
from kkl_bench.suite.tracks import get_track
from kkl_bench.support.convergence import reached_cap
from kkl_bench.support.devices import resolve as resolve_device
from kkl_bench.support.executors import execute
from kkl_bench.support.provenance import is_clean_commit, provenance


@dataclass(frozen=True)
class PlannedJob:
    """One harness job of a regeneration, with the spec of its row's run, its estimated
    wall time (s, one thread, from the source cells' records) split into ``fit_s``, the
    training of the models it is the first to need, and ``scoring_s``, the scoring of its
    cells; the processor seconds its killed attempts already spent
    (:func:`~kkl_bench.run.ledger.killed_attempts`); and ``rate``, how many times their
    estimates the finished jobs of its row took in this regeneration
    (:func:`measured_rates`; 1 before any of its row finished)."""

    spec: RunSpec
    job: Job
    fit_s: float
    scoring_s: float
    banked_s: float = 0.0
    rate: float = 1.0
    fit: tuple[Task, ...] = ()
    """The tasks of the job's fit, those already done included (empty: the job's own):
    what its ledger key names, so that a job resumed after a killed attempt wrote some of
    its cells keeps that attempt's key, and with it its meter."""
    earlier_cells: int = 0
    """The cells of its fit that its killed attempts wrote."""
    models: frozenset[tuple] = frozenset()
    """The models it trains or loads that are not trained yet (:meth:`_CostRecords.models`):
    it does not run beside another job that needs one of them before either has finished."""

    @property
    def estimate_s(self) -> float:
        return self.fit_s + self.scoring_s

    @property
    def trains(self) -> bool:
        """Whether it trains a model. A job that trains nothing only scores: its models
        made the target folder's cells of other tracks (a resumed regeneration), or an
        earlier job of the plan trains them, or its source cells recorded no training
        time."""
        return self.fit_s > 0

    @property
    def expected_s(self) -> float:
        """Its estimate with its training at the rate measured so far (the work the
        progress bar expects of it, :class:`WorkDone`): a row's rate is
        training-dominated, and a job that trains nothing keeps its scoring estimate."""
        return self.fit_s * self.rate + self.scoring_s

    @property
    def key(self) -> str:
        job = self.job
        return job_key(Job(job.estimator, job.system, self.fit or job.tasks, job.seed))


def job_key(job: Job) -> str:
    """A job's name in the ledger: row, system, seed and its tasks' ids (those of its whole
    fit: :attr:`PlannedJob.fit`)."""
    tasks = ",".join(task.id for task in job.tasks)
    return f"{job.estimator} {job.system} seed{job.seed} [{tasks}]"


@dataclass(frozen=True)
class Plan:
    """The jobs still to run, with how many of the selected source cells they make and
    how many the target folder already holds."""

    jobs: list[PlannedJob]
    cells: int
    done: int
    rates: MeasuredRates | None = None

    @property
    def estimate_s(self) -> float:
        return sum(planned.estimate_s for planned in self.jobs)

    @property
    def expected_s(self) -> float:
        """The estimate with each job at its row's measured rate (:attr:`PlannedJob.rate`)."""
        return sum(planned.expected_s for planned in self.jobs)

    def describe(self) -> str:
        """The plan in a few lines: rows, jobs (fits and scoring only), cells, estimated
        core-hours, and the expected core-hours per system (to split the work by
        ``--system`` between machines or processes)."""
        rows = pd.Series([planned.job.estimator for planned in self.jobs]).value_counts()
        lines = [
            f"{len(self.jobs)} jobs of {rows.size} rows to make {self.cells - self.done} "
            f"cells ({self.done} of {self.cells} already done): {_fits(self.jobs)}; estimated "
            f"{self.estimate_s / 3600:.1f} core-hours (from the source cells' recorded "
            "training and scoring times, one thread a job)"
        ]
        by_row = {row: [p for p in self.jobs if p.job.estimator == row] for row in rows.index}
        lines += [
            f"  {row}: {_fits(jobs)}, {sum(p.estimate_s for p in jobs) / 3600:.2f} core-hours"
            for row, jobs in sorted(
                by_row.items(), key=lambda item: -sum(p.estimate_s for p in item[1])
            )
        ]
        resumed = [planned for planned in self.jobs if planned.banked_s > 0]
        if resumed:
            lines.append(
                f"{len(resumed)} of the jobs resume killed attempts, which spent "
                f"{sum(p.banked_s for p in resumed) / 3600:.2f} core-hours"
            )
        if self.rates is not None:
            lines.append(self.rates.describe(self.expected_s))
        if self.jobs:
            lines.append(self._per_system())
        return "\n".join(lines)

    def _per_system(self) -> str:
        """The expected core-hours of each system's jobs, most first."""
        hours = pd.Series(
            [planned.expected_s / 3600 for planned in self.jobs],
            index=[planned.job.system for planned in self.jobs],
        )
        per_system = hours.groupby(level=0, sort=False).sum().sort_values(ascending=False)
        at = "at the rates above" if self.rates is not None else "estimated"
        return (
            f"Per system, {at}: "
            + ", ".join(f"{system} {value:.1f}" for system, value in per_system.items())
            + " core-hours (`--system` runs some of them: runs on disjoint systems share one "
            "target folder and its ledger side by side)"
        )


def _fits(jobs: list[PlannedJob]) -> str:
    """How many of ``jobs`` train a model and how many only score."""
    fits = sum(planned.trains for planned in jobs)
    return f"{fits} fits, {len(jobs) - fits} scoring only"


@dataclass(frozen=True)
class MeasuredRates:
    """How many times their estimates the jobs a regeneration finished took (processor
    seconds over estimated seconds, from its ledger), per row, per row and track, and over
    all. Estimates come from the source cells' records, made on another machine, at
    another commit and often under another training rule, and the rates differ widely
    between rows and, for one row, between tracks (a track's source cells were trained
    under budgets of their own), so a job's training is counted at its row's rate on its
    track where that is known, else at its row's."""

    by_row: dict[str, float]
    overall: float
    jobs: int
    by_track: dict[tuple[str, str], float] = field(default_factory=dict)
    """``(row, track)``: the rate of that row's finished jobs of that track."""
    superseded: dict[str, float] = field(default_factory=dict)
    """The rows with no finished job but jobs superseded by a redo (:func:`redo`): the
    rate those took, the best measure of the row's cost at hand."""

    def rate(self, row: str, track: str | None = None) -> float:
        """``row``'s measured rate on ``track``, else its rate over every track, else that
        of its superseded jobs; 1 (its estimate) for a row with none of those."""
        return self.by_track.get((row, track), self.by_row.get(row, self.superseded.get(row, 1.0)))

    def describe(self, expected_s: float) -> str:
        rows = ", ".join(
            f"{row} {rate:.2f}{self._tracks_of(row)}" for row, rate in self.by_row.items()
        )
        return (
            f"The {self.jobs} jobs finished in this folder took {self.overall:.2f} times "
            f"their estimates; per row: {rows}. With the training of each of those rows at "
            f"its rate (on the job's track, where one of its jobs there finished)"
            f"{self._superseded()} and the others at their estimates, the jobs left take "
            f"about {expected_s / 3600:.1f} core-hours"
        )

    def _superseded(self) -> str:
        if not self.superseded:
            return ""
        rows = ", ".join(f"{row} {rate:.2f}" for row, rate in self.superseded.items())
        return f", the rows whose jobs were all made again at the rate those took ({rows}),"

    def _tracks_of(self, row: str) -> str:
        """`` (paper 1.98, hard 6.71)``: ``row``'s rate per track, where it has finished
        jobs on more than one."""
        tracks = {track: rate for (name, track), rate in self.by_track.items() if name == row}
        if len(tracks) < 2:
            return ""
        return " (" + ", ".join(f"{track} {rate:.2f}" for track, rate in tracks.items()) + ")"


class WorkDone:
    """The processor seconds a plan's jobs have spent and are expected to spend, for a
    progress bar that moves while fits train, not only when they end, and whose time left
    follows the machine's measured pace. A job has spent its killed attempts' seconds
    (``banked_s``) and, from its meter, this invocation's (its attempts started at or
    after ``since_ns``); a finished one, what the ledger records for it. A job not
    finished is expected to need its expected work (:attr:`PlannedJob.expected_s`), or
    what it has spent where that is more: a job that runs past its estimate grows the
    total instead of stopping the bar, so the bar's rate stays the processor seconds the
    jobs get per second, and its time left counts the work the other jobs are still
    expected to need."""

    def __init__(self, planned: Plan, into: Path, since_ns: int) -> None:
        self.jobs, self.into, self.since_ns = planned.jobs, into, since_ns
        self.finished: dict[str, float] = {}

    def finish(self, planned_job: PlannedJob) -> None:
        """Count ``planned_job`` at the processor seconds the ledger records for it (its
        expected work if the ledger has no record of it)."""
        record = read_ledger(self.into)["jobs"].get(planned_job.key, {})
        self.finished[planned_job.key] = record.get("seconds", planned_job.expected_s)

    def _spent(self, planned: PlannedJob) -> float:
        if planned.key in self.finished:
            return self.finished[planned.key]
        return planned.banked_s + running_seconds(self.into, planned.key, self.since_ns)

    def measure(self) -> tuple[float, float]:
        """``(spent, total)``: the seconds the jobs have spent, and those plus the work
        the unfinished ones are still expected to need (s, one thread a job)."""
        spent = {planned.key: self._spent(planned) for planned in self.jobs}
        left = sum(
            max(planned.expected_s - spent[planned.key], 0.0)
            for planned in self.jobs
            if planned.key not in self.finished
        )
        return sum(spent.values()), sum(spent.values()) + left


def measured_rates(ledger: dict[str, Any]) -> MeasuredRates | None:
    """The rates of the finished jobs of ``ledger`` (:func:`~kkl_bench.run.ledger.read_ledger`)
    whose estimates are positive, and of its superseded ones for the rows with no finished
    job; None if there are no finished jobs."""
    seconds: dict[tuple[str, str], float] = defaultdict(float)
    estimated: dict[tuple[str, str], float] = defaultdict(float)
    jobs = 0
    for key, record in ledger["jobs"].items():
        if record["estimate_s"] > 0:
            pair = (_row_of(key), _track_of(key))
            seconds[pair] += record["seconds"]
            estimated[pair] += record["estimate_s"]
            jobs += 1
    if not jobs:
        return None
    rows = dict.fromkeys(row for row, _ in seconds)
    replaced_seconds: dict[str, float] = defaultdict(float)
    replaced_estimated: dict[str, float] = defaultdict(float)
    for record in ledger.get("superseded", []):
        row = _row_of(record["key"])
        if record["estimate_s"] > 0 and row not in rows:
            replaced_seconds[row] += record["seconds"]
            replaced_estimated[row] += record["estimate_s"]
    superseded = {row: replaced_seconds[row] / replaced_estimated[row] for row in replaced_seconds}

    def rate_of(pairs: Iterable[tuple[str, str]]) -> float:
        pairs = list(pairs)
        return sum(seconds[pair] for pair in pairs) / sum(estimated[pair] for pair in pairs)

    by_row = {row: rate_of(pair for pair in seconds if pair[0] == row) for row in rows}
    by_track = {pair: rate_of([pair]) for pair in seconds}
    return MeasuredRates(by_row, rate_of(seconds), jobs, by_track, superseded)


def _row_of(key: str) -> str:
    """The row of a ledger key (:func:`job_key`)."""
    return key_parts(key)[0]


def _fit_cells(key: str) -> list[tuple[str, str, int, str]]:
    """The cells of a ledger key's fit (:func:`job_key`), each as its row, system, seed and
    task id."""
    row, system, seed, tasks = key_parts(key)
    return [(row, system, seed, task) for task in tasks]


def _track_of(key: str) -> str:
    """The track of a ledger key's fit: its first task's (:attr:`Task.id`, ``track/system/
    regime@version``, the paper track's without the prefix)."""
    parts = key_parts(key)[3][0].split("/")
    return parts[0] if len(parts) == 3 else PAPER_TRACK


def plan(
    source: pd.DataFrame,
    profile: Profile,
    into: Path,
    cache_dir: Path,
    command: str | None = None,
    device: str = "cpu",
    recompute: Iterable[Path] = (),
) -> Plan:
    """The regeneration of the cells of ``source`` (:func:`~kkl_bench.run.results.load_results`
    of the source folder, narrowed as wanted, of ``profile``) into the folder ``into``, its
    torch estimators trained on ``device`` (:mod:`kkl_bench.support.devices`), the cell
    files ``recompute`` planned as to be made again (a dry run's :attr:`Redo.cells`).

    Each row is planned as a run of that row alone over the systems, tracks and seeds of
    its source cells (``<name>+logged`` and ``<name>+truth`` rows as runs of theirs), and
    only the tasks of its source cells are kept in its jobs. Jobs come in the order the
    harness plans them, rows in the source's order, so the first KKL row trains the
    Phase-1 models the others load.
    """
    source = source[source["profile"] == profile.name]
    wanted = set(zip(source["estimator"], source["task"], source["seed"], strict=True))
    known = _CostRecords(source)
    planned, done = [], 0
    for row, cells in source.groupby("estimator", sort=False):
        derived = bool(variants.split_row(row)[1])
        spec = RunSpec(
            estimators=(row,),
            systems=tuple(dict.fromkeys(cells["system"])),
            regimes=None,
            profile=profile,
            seeds=tuple(sorted(set(cells["seed"]))),
            results_dir=into,
            cache_dir=cache_dir,
            tracks=tuple(dict.fromkeys(cells["track"])),
            command=command,
            own_rows_only=not derived,
            keep_unsupported=True,
            device=device,
            recompute=frozenset(recompute),
        )
        todo, cached = harness.plan(spec)
        finished = [(c.estimator, c.task, c.seed) for c in cached]
        done += sum(key in wanted for key in finished)
        known.made(key for key in finished if key in wanted)
        planned.append((spec, todo))
    recorded = read_ledger(into)
    rates = measured_rates(recorded)
    jobs = []
    for spec, todo in planned:
        for job in todo:
            tasks = tuple(t for t in job.tasks if (job.estimator, t.id, job.seed) in wanted)
            if not tasks:
                continue
            fit = tuple(t for t in _fit_of(spec, job) if (job.estimator, t.id, job.seed) in wanted)
            job = Job(job.estimator, job.system, tasks, job.seed)
            key = job_key(Job(job.estimator, job.system, fit, job.seed))
            attempts = killed_attempts(into, key)
            jobs.append(
                PlannedJob(
                    spec,
                    job,
                    *known.seconds(job),
                    banked_s=sum(float(spent.get("seconds", 0.0)) for spent in attempts),
                    rate=1.0 if rates is None else rates.rate(job.estimator, tasks[0].track),
                    fit=fit,
                    # the fit's cells already made, where only its killed attempts wrote
                    earlier_cells=len(fit) - len(tasks)
                    if attempts and key not in recorded["jobs"]
                    else 0,
                    models=known.models(job),
                )
            )
    return Plan(jobs, len(wanted), done, rates)


def _fit_of(spec: RunSpec, job: Job) -> list[Task]:
    """The tasks of the fit ``job`` (of ``spec``'s row, possibly with some of its tasks
    already done) is part of: :func:`~kkl_bench.run.harness.rows_and_tasks`' group."""
    first = job.tasks[0].id
    for row, tasks in harness.rows_and_tasks(spec, spec.estimators[0], job.system):
        if row == job.estimator and any(task.id == first for task in tasks):
            return tasks
    raise ValueError(f"{job_key(job)}: no fit of {spec.estimators[0]} on {job.system} has it")


class _CostRecords:
    """What the source cells recorded of their cost: per job, the seconds its models
    trained (:func:`~kkl_bench.run.results.phase_seconds`) and the seconds its cells were
    scored in."""

    def __init__(self, source: pd.DataFrame) -> None:
        self.cells = {
            (row.estimator, row.task, row.seed): row for row in source.itertuples(index=False)
        }
        self.trained: set[tuple] = set()
        self.made_models: set[tuple] = set()

    def made(self, cells) -> None:
        """Count as trained the models of the cells ``(row, task id, seed)`` the target
        folder already holds (a resumed regeneration): the jobs that share them load them."""
        for key in cells:
            cell = self.cells[key]
            for phase, seconds in phase_seconds(cell).items():
                self.made_models.add((cell.system, cell.seed, phase, seconds))
        self.trained |= self.made_models

    def models(self, job: Job) -> frozenset[tuple]:
        """The models ``job`` trains or loads (:func:`~kkl_bench.run.results.trained_models`)
        that no cell in the target folder was made from: the jobs that share one train it
        once, so they should not run at once (:class:`~kkl_bench.support.executors.Schedule`)."""
        return trained_models(self.cells[(job.estimator, job.tasks[0].id, job.seed)]) - (
            self.made_models
        )

    def seconds(self, job: Job) -> tuple[float, float]:
        """The estimated wall time of ``job``: the seconds its models train and the seconds
        its cells are scored in. A model several jobs share (a Phase-1 model the KKL rows
        load, the nominal network a ``+logged`` row fine-tunes, one model scored on several
        tracks) reads the same training seconds in each: it is counted by the first job
        that needs it only, and not at all if a cell made from it is already in the target
        folder."""
        cells = [self.cells[(job.estimator, task.id, job.seed)] for task in job.tasks]
        fit = 0.0
        for phase, seconds in phase_seconds(cells[0]).items():
            shared = (job.system, job.seed, phase, seconds)
            if shared not in self.trained:
                self.trained.add(shared)
                fit += seconds
        scoring = sum(
            scoring_seconds(cell, task.definition.n_samples)
            for cell, task in zip(cells, job.tasks, strict=True)
        )
        return fit, scoring


def _timed_job(spec: RunSpec, job: Job, key: str) -> tuple[JobOutcome, dict[str, float], str]:
    """:func:`~kkl_bench.run.harness.run_job` on one thread, metered under ``key`` in the
    target folder, with the times it took (:func:`~kkl_bench.run.ledger.metered`:
    ``seconds``, the processor time, the core-seconds it used whatever else shares the
    machine, waits for another job's model or pauses; ``wall_seconds``) and the device its
    torch estimators were given, as the worker resolved it."""
    with metered(spec.results_dir, key) as spent:
        outcome = harness.run_job(spec, job)  # on one thread (kkl_bench.support.executors)
        return outcome, spent(), resolve_device(spec.device)


def run(
    planned: Plan,
    into: Path,
    progress: Callable[[PlannedJob, JobOutcome], None] | None = None,
    jobs: int = 1,
    executor: str = "loky",
    scheduler: str | None = None,
) -> dict[str, Any]:
    """Run ``planned``'s jobs (``jobs`` at once, through
    :func:`~kkl_bench.support.executors.execute`), adding each finished job's processor
    and wall time, with its killed attempts', to the ledger in ``into`` as it ends;
    ``progress(planned_job, outcome)`` after each. Jobs that share a model not trained
    yet (:attr:`PlannedJob.models`) do not run at once: the first to start trains it while
    the workers take other jobs, instead of one waiting on its lock. Returns the ledger."""
    by_job = {planned_job.job: planned_job for planned_job in planned.jobs}
    arguments = [(p.spec, p.job, p.key) for p in planned.jobs]
    claims = [planned_job.models for planned_job in planned.jobs]
    for outcome, times, device in execute(
        _timed_job, arguments, jobs, executor, scheduler, claims=claims
    ):
        planned_job = by_job[outcome.job]
        failed = sum(cell.status == "error" for cell in outcome.scored)
        earlier = interrupted_times(into, planned_job.key)
        record_job(
            into,
            planned_job.key,
            {name: seconds + earlier[name] for name, seconds in times.items()},
            planned_job.estimate_s,
            len(outcome.scored) + planned_job.earlier_cells,
            failed,
            device,
        )
        if progress is not None:
            progress(planned_job, outcome)
    return read_ledger(into)


@dataclass(frozen=True)
class Redo:
    """What :func:`redo` made to be computed again in a regeneration's folder: the cell
    files it removed and the ledger jobs it superseded (or would, in a dry run)."""

    rows: tuple[str, ...]
    cells: tuple[Path, ...]
    jobs: tuple[str, ...]
    commit: str
    dry_run: bool = False
    capped_only: bool = False

    def describe(self) -> str:
        verb = "would make" if self.dry_run else "makes"
        which = "whose fit reached a cap and " if self.capped_only else ""
        return (
            f"--redo {' '.join(self.rows)} {verb} {len(self.cells)} cells again (those "
            f"{which}not written at {self.commit}) and supersedes {len(self.jobs)} jobs of "
            "the ledger"
        )


def redo(
    source: pd.DataFrame,
    profile: Profile,
    into: Path,
    rows: Iterable[str],
    because: str,
    dry_run: bool = False,
    capped_only: bool = False,
) -> Redo:
    """Make ``rows``' cells of ``source`` (a selection, :func:`select`) again in ``into``
    where the code at hand did not write them, after a change of those rows' training was
    committed: each of their cell files in ``into`` that names another commit than today's
    is removed, with its kept estimate, and the ledger's jobs of another commit that made
    one of them are moved to its ``superseded`` list with ``because``
    (:func:`~kkl_bench.run.ledger.supersede`), what they spent kept apart. With
    ``capped_only``, only the cells whose fit reached a cap
    (:func:`~kkl_bench.support.convergence.reached_cap`), and the other cells of their jobs:
    after a cap was raised, the fits the plateau rule stopped would come back bit for
    bit. Cells written at today's commit stay, so a resumed redo removes nothing it made.
    With ``dry_run`` nothing is removed. Raises ValueError if the code is not a clean
    commit, ``into`` holds no regeneration's ledger, or a row is not in ``source``."""
    commit = provenance()["git_commit"]
    if not is_clean_commit(commit):
        raise ValueError(
            f"--redo makes cells again where another commit wrote them, so the code must be "
            f"a clean commit; it is {commit}"
        )
    if not (Path(into) / LEDGER_FILE).exists():
        raise ValueError(
            f"{into} holds no ledger of a regeneration ({LEDGER_FILE}): --redo removes only "
            "the cells a regeneration wrote"
        )
    rows = tuple(rows)
    elsewhere, wanted = {}, set()  # (row, system, seed, task id): cells of another commit
    for cell in select(source, rows).itertuples():
        path = cell_path(
            into, cell.estimator, cell.system, cell.regime, profile.name, cell.seed, cell.track
        )
        if not path.exists():
            continue
        record = read_cell(path)
        if record.provenance.get("git_commit") == commit:
            continue
        name = (cell.estimator, cell.system, cell.seed, cell.task)
        elsewhere[name] = path
        if not capped_only or reached_cap(record.fit_report):
            wanted.add(name)
    fits = {
        key: _fit_cells(key)
        for key, record in read_ledger(into)["jobs"].items()
        if record["git_commit"] != commit
    }
    jobs = [key for key, cells in fits.items() if not wanted.isdisjoint(cells)]
    # every cell of a superseded job, so that the ledger's jobs still account for each cell
    remade = wanted.union(*(fits[key] for key in jobs))
    stale = [path for name, path in elsewhere.items() if name in remade]
    if not dry_run:
        supersede(into, jobs, because)
        for path in stale:
            estimate_path(path).unlink(missing_ok=True)
            path.unlink()
    return Redo(rows, tuple(stale), tuple(jobs), commit, dry_run, capped_only)


def select(
    source: pd.DataFrame,
    rows: Iterable[str] | None = None,
    tracks: Iterable[str] | None = None,
    systems: Iterable[str] | None = None,
) -> pd.DataFrame:
    """The cells of ``source`` of the given rows, tracks and systems (None: all), each name
    checked against those the source holds."""
    for column, wanted in (("estimator", rows), ("track", tracks), ("system", systems)):
        if wanted is None:
            continue
        wanted = list(wanted)
        present = list(dict.fromkeys(source[column]))
        unknown = [name for name in wanted if name not in present]
        if unknown:
            raise ValueError(
                f"the source results hold no {column} {', '.join(map(repr, unknown))}; "
                f"valid: {', '.join(present)}"
            )
        source = source[source[column].isin(wanted)]
    for track in set(source["track"]):
        get_track(track)  # a track the cells name must still exist
    return source
