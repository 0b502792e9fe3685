"""What a run is asked to do (:class:`RunSpec`), and the fit context each estimator of it gets."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from kkl_bench import variants
from kkl_bench.cache import default_cache_dir
from kkl_bench.devices import check_device
from kkl_bench.estimator import FitContext
from kkl_bench.plants import logged_data
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.simulate import Trajectories
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import estimators, systems
from kkl_bench.task import Profile, Task
from kkl_bench.tracks import Plant, TrackError, get_track
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
    """Where torch estimators train (:mod:`kkl_bench.devices`); resolved by each worker."""
    command: str | None = None
    """The command line that started the run (``kkl-bench run ...``), recorded in every
    cell's provenance; None when the harness is called from Python."""

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
                        f"valid regimes: {', '.join(sorted(names))}"
                    )
        if not self.tasks():
            raise ValueError(
                f"track(s) {', '.join(self.tracks)} have no task for system(s) "
                f"{', '.join(self.systems)}"
            )
        check_device(self.device)
        if not self.seeds:
            raise ValueError("no seeds selected")
        if any(seed < 0 for seed in self.seeds):
            raise ValueError(f"seeds must be non-negative integers, got {list(self.seeds)}")
        canonical = tuple(dict.fromkeys(variants.canonical(name) for name in self.estimators))
        object.__setattr__(self, "estimators", canonical)
        object.__setattr__(self, "seeds", tuple(dict.fromkeys(self.seeds)))
        object.__setattr__(self, "tracks", tuple(dict.fromkeys(self.tracks)))

    def tasks(self, system: str | None = None) -> list[Task]:
        """The selected tasks (of ``system``, or of every selected system), track by track."""
        selected = []
        for track in map(get_track, self.tracks):
            for name in self.systems if system is None else (system,):
                if name not in track.systems:
                    continue
                selected += [
                    Task(name, task, track.version, track.name)
                    for task in track.task_names()
                    if self.regimes is None or task in self.regimes
                ]
        return selected

    def seeds_for(self, estimator: str) -> tuple[int, ...]:
        """The seeds ``estimator`` runs with: all, or the first if it ignores the seed."""
        uses_seed = estimators.get(variants.base_name(estimator)).uses_seed
        return self.seeds if uses_seed else self.seeds[:1]


def make_fit_context(
    spec: RunSpec, estimator: str, system: str, seed: int, logged_data: Trajectories | None = None
) -> FitContext:
    """The context ``estimator`` (a name or variant) is fitted with for ``system`` and ``seed``
    (with ``logged_data``, the trajectories logged on a true plant, if given)."""
    model = systems.get(system)()
    return FitContext(
        system=model,
        dt=DT,
        n_samples=N_SAMPLES,
        sigma_w=SIGMA_W,
        sigma_v=SIGMA_V,
        training=TrainingData(model, DT, N_SAMPLES, SIGMA_W, SIGMA_V, seed),
        seed=seed,
        profile=spec.profile.name,
        budget=spec.profile.budget_for(variants.base_name(estimator)),
        cache_dir=Path(spec.cache_dir),
        logged_data=logged_data,
        device=spec.device,
    )


def plant_of(tasks: Iterable[Task]) -> tuple[str, Plant]:
    """The one ``(track, plant)`` that ``tasks`` share (the tasks of a ``+logged`` fit)."""
    plants = {(task.track, task.definition().plant) for task in tasks}
    if len(plants) != 1:
        raise ValueError(f"tasks of {len(plants)} different plants in one fit with logged data")
    return plants.pop()


def fit_context_for_row(
    spec: RunSpec, row: str, system: str, tasks: Iterable[Task], seed: int
) -> FitContext:
    """The fit context of result row ``row``: an estimator (variant), or ``<name>+logged``,
    which also receives the data logged on the plant of ``tasks``."""
    name, with_logged = variants.split_logged(row)
    if not with_logged:
        return make_fit_context(spec, name, system, seed)
    track, plant = plant_of(tasks)
    logged = logged_data(system, plant, track, SIGMA_W, SIGMA_V)
    return make_fit_context(spec, name, system, seed, logged)
