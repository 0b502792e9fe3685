"""What a run is asked to do (:class:`RunSpec`), and the fit context each estimator of it gets."""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kkl_bench import variants
from kkl_bench.estimator import FitContext
from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import did_you_mean, estimators, systems
from kkl_bench.suite.plants import logged_data
from kkl_bench.suite.task import Profile, Task
from kkl_bench.suite.tracks import (
    TRACKS_ENV,
    Plant,
    TrackError,
    get_track,
    template_name,
    track_template,
    tracks_of,
)
from kkl_bench.support.cache import default_cache_dir
from kkl_bench.support.device_names import check_device
from kkl_bench.training import TrainingData


@dataclass(frozen=True)
class RunSpec:
    """What to run: the grid, the profile, the training seeds and where results go.

    ``estimators`` are registered names or variants of them
    (``static_hyperkkl[guard=True]``, see :mod:`kkl_bench.variants`); they are
    stored in their canonical spelling. ``regimes`` are task names of the
    ``tracks`` (each must belong to at least one), or None for all of them.
    """

    estimators: tuple[str, ...]
    systems: tuple[str, ...]
    regimes: tuple[str, ...] | None
    profile: Profile
    seeds: tuple[int, ...] = (0,)
    results_dir: Path = Path("results")
    cache_dir: Path = field(default_factory=default_cache_dir)
    force: bool = False
    tracks: tuple[str, ...] = (PAPER_TRACK,)
    device: str = "auto"
    """Where torch estimators train (:mod:`kkl_bench.support.devices`); resolved by each worker."""
    command: str | None = None
    """The command line that started the run (``kkl-bench run ...``), recorded in every
    cell's provenance; None when the harness is called from Python."""
    own_rows_only: bool = False
    """Fit each estimator for its own row only: not its ``+logged`` row (fitted anew on
    each true plant's logged data) nor its ``+truth`` row (to score the own row's cells
    again after its fit changed, without the others' fits)."""
    keep_unsupported: bool = False
    """Keep the cells already decided ``unsupported`` like finished ones. A run decides
    them anew (no fit: a plugin that gains support gets its cells); a regeneration, meant
    to run one commit's code across its invocations, keeps them, so that what it has left
    to do comes to nothing."""
    recompute: frozenset[Path] = frozenset()
    """Cell files planned as to be computed again though they are on disk: those a dry run
    of ``kkl-bench regenerate --redo`` would remove."""

    def __post_init__(self) -> None:
        if not self.estimators:
            raise ValueError("no estimators selected")
        if not self.systems:
            raise ValueError("no systems selected")
        for name in self.systems:
            if name not in systems:
                systems.get(name)  # raises the error listing the valid names
        if not self.tracks:
            raise ValueError("no tracks selected")
        tracks = [get_track(name) for name in self.tracks]
        if self.regimes is not None:
            if not self.regimes:
                raise ValueError("no regimes selected")
            names = {name for track in tracks for name in track.task_names()}
            for regime in self.regimes:
                if regime not in names:
                    raise TrackError(
                        f"unknown regime {regime!r} for track(s) {', '.join(self.tracks)}; "
                        f"valid regimes: {', '.join(sorted(names))}{did_you_mean(regime, names)}"
                    )
        if not self.tasks():
            raise TrackError(_no_task_message(self.systems, self.tracks))
        check_device(self.device)
        if not self.seeds:
            raise ValueError("no seeds selected")
        if any(seed < 0 for seed in self.seeds):
            raise ValueError(f"seeds must be non-negative integers, got {list(self.seeds)}")
        derived = [name for name in self.estimators if variants.split_row(name)[1]]
        if self.own_rows_only and derived:
            raise ValueError(
                f"own rows only, but {', '.join(map(repr, derived))} "
                f"{'is' if len(derived) == 1 else 'are'} not an estimator's own row"
            )
        canonical = tuple(dict.fromkeys(variants.canonical(name) for name in self.estimators))
        object.__setattr__(self, "estimators", canonical)
        object.__setattr__(self, "seeds", tuple(dict.fromkeys(self.seeds)))
        object.__setattr__(self, "tracks", tuple(dict.fromkeys(self.tracks)))

    @functools.cached_property
    def _tasks(self) -> tuple[Task, ...]:
        """Every selected task, resolved once (:class:`~kkl_bench.suite.task.Task`), track
        by track, system by system."""
        selected = []
        for track in map(get_track, self.tracks):
            for name in self.systems:
                if name not in track.systems:
                    continue
                selected += [
                    Task(name, task, track.version, track.name)
                    for task in track.task_names()
                    if self.regimes is None or task in self.regimes
                ]
        return tuple(selected)

    def tasks(self, system: str | None = None) -> list[Task]:
        """The selected tasks (of ``system``, or of every selected system), track by track,
        each resolved once for the whole run."""
        return [task for task in self._tasks if system is None or task.system == system]

    def seeds_for(self, estimator: str) -> tuple[int, ...]:
        """The seeds ``estimator`` runs with: all, or the first if it ignores the seed."""
        uses_seed = estimators.get(variants.base_name(estimator)).uses_seed
        return self.seeds if uses_seed else self.seeds[:1]


def _no_task_message(systems: tuple[str, ...], tracks: tuple[str, ...]) -> str:
    """Why the ``tracks`` asked for hold no task for ``systems``, and what to do: the tracks
    that do list them, or, for a system no track lists, the track file to write."""
    lines = [f"track(s) {', '.join(tracks)} have no task for system(s) {', '.join(systems)}"]
    for system in systems:
        listed = tracks_of(system)
        if listed:
            lines.append(f"  {system} is on track(s) {', '.join(listed)}: pass --track {listed[0]}")
            continue
        name = template_name(system)
        lines += [
            f"  {system} is on no track: a track file says which tasks a system runs. Write",
            f"  this one as tracks/{name}.toml (any folder of track files),",
            "",
            *(f"    {line}".rstrip() for line in track_template(system).splitlines()),
            "",
            f"  then run with that folder in ${TRACKS_ENV}, e.g. {TRACKS_ENV}=tracks "
            f"kkl-bench run ... --system {system} --track {name}",
        ]
    return "\n".join(lines)


@dataclass(frozen=True)
class FitConditions:
    """What an estimator is told of the tasks it is fitted for, where that is not the
    protocol's: the measurement model (its noise scale ``sigma_v``) and, for a ``+truth``
    row, the box the initial states come from (``None``: the system's)."""

    measurement: MeasurementModel
    x0_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None


PROTOCOL_CONDITIONS = FitConditions(MeasurementModel())


def task_conditions(task: Task, with_box: bool = False) -> FitConditions:
    """The conditions of ``task`` (with its initial box when ``with_box``)."""
    definition = task.definition
    box = None
    if with_box:
        low, high = definition.x0_box.for_system(systems.get(task.system)())
        box = (tuple(np.asarray(low, dtype=float)), tuple(np.asarray(high, dtype=float)))
    return FitConditions(definition.measurement, box)


def fit_groups(tasks: Iterable[Task]) -> list[tuple[FitConditions, list[Task]]]:
    """``tasks`` grouped by the conditions their estimators are fitted with: the protocol's,
    except on a track fitted per task (``fitted_per_task``), where each measurement
    model has its own fit."""
    groups: dict[FitConditions, list[Task]] = {}
    for task in tasks:
        per_task = task.fitted_per_task
        conditions = task_conditions(task) if per_task else PROTOCOL_CONDITIONS
        groups.setdefault(conditions, []).append(task)
    return list(groups.items())


def truth_groups(tasks: Iterable[Task]) -> list[tuple[FitConditions, list[Task]]]:
    """The tasks of a ``+truth`` row, grouped by their truth: those of tracks that test
    generalization (not fitted per task, nominal plant) whose noise, measurement model or
    initial box differ from what the protocol's fit is told."""
    protocol: dict[str, FitConditions] = {}
    groups: dict[FitConditions, list[Task]] = {}
    for task in tasks:
        definition = task.definition
        if task.fitted_per_task or not definition.plant.nominal:
            continue
        truth = task_conditions(task, with_box=True)
        if task.system not in protocol:
            model = systems.get(task.system)()
            box = (tuple(model.x0_low.astype(float)), tuple(model.x0_high.astype(float)))
            protocol[task.system] = FitConditions(MeasurementModel(), box)
        if truth != protocol[task.system]:
            groups.setdefault(truth, []).append(task)
    return list(groups.items())


def conditioned_context(
    system: str, seed: int, conditions: FitConditions = PROTOCOL_CONDITIONS, **fields
) -> FitContext:
    """The fit context for ``system`` and ``seed`` under ``conditions``: the model read
    through their sensor, the training generator simulating their measurement model, the
    initial box they give; ``fields`` set the rest (budget, cache, ...)."""
    measurement = conditions.measurement
    model = measurement.system(systems.get(system)())
    box = None if conditions.x0_box is None else tuple(map(np.array, conditions.x0_box))
    return FitContext(
        system=model,
        dt=DT,
        n_samples=N_SAMPLES,
        sigma_w=SIGMA_W,
        sigma_v=measurement.sigma,
        training=TrainingData(model, DT, N_SAMPLES, SIGMA_W, measurement.sigma, seed, measurement),
        seed=seed,
        measurement=measurement,
        x0_box=box,
        **fields,
    )


def make_fit_context(
    spec: RunSpec,
    estimator: str,
    system: str,
    seed: int,
    logged_data: Trajectories | None = None,
    conditions: FitConditions = PROTOCOL_CONDITIONS,
) -> FitContext:
    """The context ``estimator`` (a name or variant) is fitted with for ``system`` and ``seed``
    in the run ``spec`` (with ``logged_data``, the trajectories logged on a true plant, if
    given, and the ``conditions`` of the tasks it is fitted for)."""
    return conditioned_context(
        system,
        seed,
        conditions,
        profile=spec.profile.name,
        budget=spec.profile.budget_for(
            variants.base_name(estimator), variants.split_row(estimator)[0]
        ),
        cache_dir=Path(spec.cache_dir),
        logged_data=logged_data,
        device=spec.device,
    )


def plant_of(tasks: Iterable[Task]) -> tuple[str, Plant]:
    """The one ``(track, plant)`` that ``tasks`` share (the tasks of a ``+logged`` fit)."""
    plants = {(task.track, task.definition.plant) for task in tasks}
    if len(plants) != 1:
        raise ValueError(f"tasks of {len(plants)} different plants in one fit with logged data")
    return plants.pop()


def fit_context_for_row(
    spec: RunSpec, row: str, system: str, tasks: Iterable[Task], seed: int
) -> FitContext:
    """The fit context of result row ``row`` for ``tasks``: an estimator (variant), fitted
    with the conditions of ``tasks`` (:func:`fit_groups`); ``<name>+logged``, which also
    receives the data logged on the plant of ``tasks``; or ``<name>+truth``, fitted with
    the truth of ``tasks`` (:func:`truth_groups`)."""
    tasks = list(tasks)
    name, suffix = variants.split_row(row)
    if suffix == variants.LOGGED:
        track, plant = plant_of(tasks)
        logged = logged_data(system, plant, track, SIGMA_W, SIGMA_V)
        return make_fit_context(spec, name, system, seed, logged)
    groups = truth_groups(tasks) if suffix == variants.TRUTH else fit_groups(tasks)
    if len(groups) != 1 or len(groups[0][1]) != len(tasks):
        raise ValueError(f"row {row!r}: the tasks {[str(t) for t in tasks]} need different fits")
    return make_fit_context(spec, name, system, seed, conditions=groups[0][0])
