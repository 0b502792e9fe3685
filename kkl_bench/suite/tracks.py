"""Tracks: named, versioned sets of tasks, each declared in one TOML file (protocol section 7).

A track says which systems it covers and, per task, the input family and its
parameter ranges, the measurement and process noise, the box initial states
are drawn from and the horizon. Estimators are never fitted for a track:
they are fitted once, as the paper's protocol says, and scored on every
track asked for. The built-in tracks are ``tasks/tracks/*.toml``; directories
listed in ``$KKL_BENCH_TRACKS`` (separated by ``:``) add more, with no code.

A track file::

    name = "noise"                 # lower case, digits and '-'
    version = 1                    # task ids end in @v<version>
    description = "..."
    systems = ["duffing", "vdp"]
    settling = false               # show the settling-time column in its tables
    fitted_per_task = false        # true: every estimator is fitted for each task's
                                   # measurement model and noise (the ``hard`` track);
                                   # false: fitted once with the protocol's, as in the paper

    [defaults]                     # any task field below, for every task
    measurement_noise = 0.01       # standard deviation of v_k (the paper's: 0.01)
    process_noise = 0.01           # standard deviation of w_k (the paper's: 0.01)
    horizon = 50.0                 # s, a whole number of protocol steps
    x0_box = {scale = 1.0}         # the system's box, half-widths scaled about
                                   # its centre; [x0_box.<system>] low/high replace it
    plant = {parameters = 0.1, sensor_gain = 1.05, sensor_offset = 0.02}
                                   # the data come from a plant unlike the nominal
                                   # model (see Plant); default: the nominal model
    measurement = {sensor = "quantized", step = 0.5, observe_every = 5, noise = "student-t", dof = 3}
                                   # how the state is observed (kkl_bench.measurement):
                                   # a registered sensor and its parameters, the
                                   # sampling and the noise law (scale: measurement_noise);
                                   # default: h(x) + Gaussian noise at every sample

    [[task]]
    name = "sinusoid-sigma0.1"     # unique within the track
    family = "sinusoid"            # a registered input regime
    reference = "sinusoid"         # the paper task it is compared with (default: family)
    amplitude = [0.5, 1.0]         # the family's parameters (ranges)
    measurement_noise = 0.1
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import os
import re
import sys
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kkl_bench.measurement import MeasurementModel, with_scale
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.protocol.signals import Regime
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import did_you_mean, regimes, systems
from kkl_bench.suite.track_fields import (
    Plant,
    TrackError,
    X0Box,
    parse_measurement,
    parse_number,
    parse_plant,
    parse_x0_box,
)

TRACKS_ENV = "KKL_BENCH_TRACKS"
"""Environment variable: more directories of track files, separated by ``:``."""
TASK_FIELDS = (
    "name",
    "family",
    "reference",
    "measurement_noise",
    "process_noise",
    "horizon",
    "x0_box",
    "plant",
    "measurement",
)
"""Fields every task (and ``[defaults]``, except name and family) may set; the rest go to the family."""
_NAME = re.compile(r"[a-z0-9][a-z0-9-]*")
_TASK_NAME = re.compile(r"[a-z0-9][a-z0-9_.-]*")


@dataclass(frozen=True)
class TaskDefinition:
    """One task of a track, for every system of the track.

    Attributes
    ----------
    name: the task's name, the ``<regime>`` of its id ``<track>/<system>/<regime>@v<n>``.
    family: the registered input regime its signals come from.
    params: the family's keyword arguments, as ``(name, value)`` pairs.
    reference: the paper task the cross-track summary compares it with.
    sigma_v, sigma_w: measurement and process noise standard deviations.
    horizon: s; the test trajectories have ``n_samples = horizon / DT + 1`` samples.
    x0_box: where initial states are drawn from.
    plant: how the plant making the data differs from the nominal model.
    measurement: how the states are observed (its noise scale is ``sigma_v``).
    """

    name: str
    family: str
    params: tuple[tuple[str, Any], ...] = ()
    reference: str = ""
    sigma_v: float = SIGMA_V
    sigma_w: float = SIGMA_W
    horizon: float = (N_SAMPLES - 1) * DT
    x0_box: X0Box = X0Box()  # noqa: RUF009 (frozen: one shared default is safe)
    plant: Plant = Plant()  # noqa: RUF009 (frozen)
    measurement: MeasurementModel | None = None
    """None: ``h(x)`` plus Gaussian noise of ``sigma_v`` at every sample."""

    def __post_init__(self) -> None:
        measurement = with_scale(self.measurement, self.sigma_v, f"task {self.name!r}")
        object.__setattr__(self, "measurement", measurement)

    @property
    def n_samples(self) -> int:
        return round(self.horizon / DT) + 1

    def regime(self) -> Regime:
        """The input regime with this task's parameters."""
        return regimes.get(self.family)(**dict(self.params))


@dataclass(frozen=True)
class Track:
    """A named, versioned set of tasks (see the module docstring for the file format)."""

    name: str
    version: int
    description: str
    systems: tuple[str, ...]
    tasks: tuple[TaskDefinition, ...]
    settling: bool = False
    source: str = ""
    fitted_per_task: bool = False
    """Whether estimators are fitted for each task's measurement model (protocol 7.6)."""
    by_system: tuple[tuple[str, str, TaskDefinition], ...] = ()
    """``(task, system, definition)`` where a field set by system (``{default = ..,
    <system> = ..}``) gives that system another definition than ``tasks``'."""

    def task_names(self) -> list[str]:
        return [task.name for task in self.tasks]

    def task(self, name: str, system: str | None = None) -> TaskDefinition:
        """The task ``name`` (for ``system``, where a field is set by system); the error lists
        the track's tasks."""
        for task_name, system_name, definition in self.by_system:
            if (task_name, system_name) == (name, system):
                return definition
        for task in self.tasks:
            if task.name == name:
                return task
        raise TrackError(
            f"track {self.name!r} has no task {name!r}; its tasks: {', '.join(self.task_names())}"
        )


def parse_track(text: str, source: str = "<string>") -> Track:
    """The track declared by the TOML ``text`` (``source`` names it in errors)."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise TrackError(f"{source}: not valid TOML: {error}") from None

    def fail(where: str, message: str) -> TrackError:
        return TrackError(f"{source}: {where}: {message}")

    known = {
        "name",
        "version",
        "description",
        "systems",
        "settling",
        "fitted_per_task",
        "defaults",
        "task",
    }
    for key in table:
        if key not in known:
            raise fail(f"field {key!r}", f"unknown field; a track sets {', '.join(sorted(known))}")
    name = table.get("name")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise fail("field 'name'", f"must be lower-case letters, digits and '-', got {name!r}")
    version = table.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise fail("field 'version'", f"must be a positive integer, got {version!r}")
    listed = table.get("systems")
    if not isinstance(listed, list) or not listed or not all(isinstance(s, str) for s in listed):
        raise fail("field 'systems'", f"must be a non-empty list of system names, got {listed!r}")
    for system in listed:
        if system not in systems:
            raise fail(
                "field 'systems'",
                f"unknown system {system!r}; valid systems: {', '.join(systems.names())}",
            )
    flags = {key: table.get(key, False) for key in ("settling", "fitted_per_task")}
    for key, value in flags.items():
        if not isinstance(value, bool):
            raise fail(f"field {key!r}", f"must be true or false, got {value!r}")
    defaults = table.get("defaults", {})
    if not isinstance(defaults, dict):
        raise fail("field 'defaults'", "must be a table")
    for key in ("name", "family"):
        if key in defaults:
            raise fail(f"[defaults] field {key!r}", "is set per task, not in [defaults]")
    entries = table.get("task")
    if (
        not isinstance(entries, list)
        or not entries
        or not all(isinstance(e, dict) for e in entries)
    ):
        raise fail("[[task]]", "a track needs at least one [[task]] table")
    tasks: list[TaskDefinition] = []
    by_system: list[tuple[str, str, TaskDefinition]] = []
    for number, entry in enumerate(entries, start=1):
        task_name = entry.get("name")
        where = f"task {task_name!r}" if isinstance(task_name, str) else f"[[task]] number {number}"
        if not isinstance(task_name, str) or not _TASK_NAME.fullmatch(task_name):
            raise fail(
                f"{where}, field 'name'",
                f"must be lower-case letters, digits, '_', '.' and '-', got {task_name!r}",
            )
        if task_name in {t.name for t in tasks}:
            raise fail(where, f"duplicate task id {name}/<system>/{task_name}")
        merged = {**defaults, **entry}
        try:
            tasks.append(_task(task_name, _for_system(merged, None, tuple(listed)), tuple(listed)))
            for system in listed:
                definition = _task(
                    task_name, _for_system(merged, system, tuple(listed)), tuple(listed)
                )
                if definition != tasks[-1]:
                    by_system.append((task_name, system, definition))
        except (TrackError, ValueError, TypeError) as error:
            raise fail(where, str(error)) from None
    return Track(
        name,
        version,
        str(table.get("description", "")),
        tuple(listed),
        tuple(tasks),
        flags["settling"],
        source,
        flags["fitted_per_task"],
        tuple(by_system),
    )


def _for_system(
    entry: Mapping[str, Any], system: str | None, track_systems: tuple[str, ...]
) -> dict[str, Any]:
    """``entry`` with every value set by system (a table with a ``default`` key, e.g.
    ``{default = 0.3, rossler = 3.0}``) replaced by ``system``'s (None: the default)."""
    resolved = {}
    for key, value in entry.items():
        if isinstance(value, dict) and "default" in value:
            unknown = sorted(set(value) - {"default", *track_systems})
            if unknown:
                raise TrackError(
                    f"field {key!r} is set for {unknown[0]!r}, not a system of this track "
                    f"({', '.join(track_systems)})"
                )
            resolved[key] = value.get(system, value["default"]) if system else value["default"]
        elif isinstance(value, dict) and key != "x0_box":
            resolved[key] = _for_system(value, system, track_systems)
        else:
            resolved[key] = value
    return resolved


def _task(name: str, entry: Mapping[str, Any], track_systems: tuple[str, ...]) -> TaskDefinition:
    """One task from its merged ``[defaults]`` and ``[[task]]`` fields."""
    family = entry.get("family")
    if not isinstance(family, str):
        raise TrackError(f"field 'family' is missing or not a name, got {family!r}")
    if family not in regimes:
        raise TrackError(
            f"field 'family': unknown family {family!r}; valid families: {', '.join(regimes.names())}"
        )
    regime_class = regimes.get(family)
    fields = {f.name: f for f in dataclasses.fields(regime_class)}
    params = {key: value for key, value in entry.items() if key not in TASK_FIELDS}
    unknown = sorted(set(params) - set(fields))
    if unknown:
        raise TrackError(
            f"unknown field {unknown[0]!r}; family {family!r} takes "
            f"{', '.join(fields) or 'no parameters'}, and every task may set {', '.join(TASK_FIELDS)}"
        )
    required = [
        key
        for key, f in fields.items()
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    missing = [key for key in required if key not in params]
    if missing:
        raise TrackError(f"family {family!r} needs parameter(s) {', '.join(missing)}")
    params = {
        key: tuple(value) if isinstance(value, list) else value for key, value in params.items()
    }
    try:
        regime_class(**params)
    except ValueError as error:
        raise TrackError(f"family {family!r}: {error}") from None
    horizon = parse_number("horizon", entry.get("horizon", (N_SAMPLES - 1) * DT), positive=True)
    if abs(horizon / DT - round(horizon / DT)) > 1e-9:
        raise TrackError(f"field 'horizon' must be a whole number of {DT} s steps, got {horizon!r}")
    reference = entry.get("reference", family)
    if not isinstance(reference, str):
        raise TrackError(f"field 'reference' must be a task name, got {reference!r}")
    sigma_v = parse_number("measurement_noise", entry.get("measurement_noise", SIGMA_V))
    return TaskDefinition(
        name=name,
        family=family,
        params=tuple(sorted(params.items())),
        reference=reference,
        sigma_v=sigma_v,
        sigma_w=parse_number("process_noise", entry.get("process_noise", SIGMA_W)),
        horizon=horizon,
        x0_box=parse_x0_box(entry.get("x0_box", {}), track_systems),
        plant=parse_plant(entry.get("plant", {})),
        measurement=parse_measurement(entry.get("measurement", {}), sigma_v),
    )


def _track_files() -> list[tuple[str, str]]:
    """``(source, text)`` of every track file: the built-in ones, then ``$KKL_BENCH_TRACKS``'s."""
    folder = importlib.resources.files("kkl_bench.tasks").joinpath("tracks")
    found = [
        (f"tasks/tracks/{entry.name}", entry.read_text())
        for entry in sorted(folder.iterdir(), key=lambda e: e.name)
        if entry.name.endswith(".toml")
    ]
    for directory in filter(None, os.environ.get(TRACKS_ENV, "").split(":")):
        path = Path(directory)
        if not path.is_dir():
            raise TrackError(f"${TRACKS_ENV} names {directory!r}, which is not a directory")
        found += [(str(file), file.read_text()) for file in sorted(path.glob("*.toml"))]
    return found


@functools.cache
def _load(environment: str) -> tuple[dict[str, Track], dict[str, str]]:
    """The tracks that parse, by name, and the broken track files: source -> reason. A
    broken file (not valid TOML, a field missing or wrong, a name already declared, a
    reference that is no paper task) is named once on stderr and skipped; the others load."""
    loaded: dict[str, Track] = {}
    broken: dict[str, str] = {}
    for source, text in _track_files():
        try:
            track = parse_track(text, source)
        except TrackError as error:
            broken[source] = str(error)
            continue
        if track.name in loaded:
            broken[source] = (
                f"{source}: track {track.name!r} is already declared in {loaded[track.name].source}"
            )
            continue
        loaded[track.name] = track
    if PAPER_TRACK in loaded:  # the default track first, then the others by file name
        loaded = {PAPER_TRACK: loaded[PAPER_TRACK], **loaded}
    paper = loaded.get(PAPER_TRACK)
    for name, track in list(loaded.items()):
        for task in track.tasks:
            if paper is not None and task.reference not in paper.task_names():
                broken[track.source] = (
                    f"{track.source}: task {task.name!r}, field 'reference': {task.reference!r} "
                    f"is not a task of the paper track ({', '.join(paper.task_names())})"
                )
                del loaded[name]
                break
    for reason in broken.values():
        print(f"kkl-bench: warning: skipped a broken track file: {reason}", file=sys.stderr)
    return loaded, broken


def load_tracks() -> dict[str, Track]:
    """Every track that loads, by name, built-in first (read once per ``$KKL_BENCH_TRACKS``
    value); broken track files are left out (:func:`broken_tracks`)."""
    return _load(os.environ.get(TRACKS_ENV, ""))[0]


def broken_tracks() -> dict[str, str]:
    """The track files that did not load: source -> reason."""
    return _load(os.environ.get(TRACKS_ENV, ""))[1]


def get_track(name: str) -> Track:
    """The track ``name``; the error lists the valid ones and suggests the closest."""
    tracks = load_tracks()
    if name not in tracks:
        raise TrackError(
            f"unknown track {name!r}; valid tracks: {', '.join(tracks)}{did_you_mean(name, tracks)}"
        )
    return tracks[name]


def tracks_of(system: str) -> list[str]:
    """The tracks that list ``system``."""
    return [name for name, track in load_tracks().items() if system in track.systems]


def template_name(system: str) -> str:
    """The name :func:`track_template` gives the track of ``system`` (a track name holds
    lower-case letters, digits and '-')."""
    return re.sub(r"[^a-z0-9-]", "-", system.lower())


def track_template(system: str) -> str:
    """A track file that runs ``system`` on the paper's four regimes (with the paper's
    noise, x0 box and horizon): what to write for a system no track lists yet."""
    tasks = "".join(
        f'\n[[task]]\nname = "{name}"\nfamily = "{name}"\n'
        for name in ("zero", "constant", "sinusoid", "square")
    )
    return (
        f'name = "{template_name(system)}"\nversion = 1\n'
        f'description = "{system} under the paper\'s four input regimes."\n'
        f'systems = ["{system}"]\n{tasks}'
    )


def find_track(name: str) -> Track | None:
    """The track ``name`` if this install declares it, else None (stored results may come
    from a track file this install does not have)."""
    return load_tracks().get(name)
