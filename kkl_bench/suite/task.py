"""Tasks, profiles and the pinned test sets (protocol sections 4 and 8).

A :class:`Task` is one (system, regime) cell of a track (:mod:`kkl_bench.suite.tracks`),
with a versioned id such as ``ood-inputs/duffing/chirp@v1``; the paper
track's ids carry no track name (``lorenz/square@v1``). Its test set is drawn
from the protocol's pinned random streams and carries two fingerprints:

* ``stream_fingerprint`` hashes the random draws (x0, regime numbers, noise).
  They come from numpy's PCG64 generator and are identical on every machine.
* ``fingerprint`` hashes the simulated arrays ``t, u, x, y``. It is identical
  wherever floating-point arithmetic (and ``numpy.sin``) round alike; the
  chaotic systems amplify any last-bit difference, so a mismatch between two
  machines with equal stream fingerprints points at the platform, not at the
  protocol.
"""

from __future__ import annotations

import functools
import importlib.resources
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from kkl_bench.protocol import DT, PROTOCOL_VERSION
from kkl_bench.protocol.metrics import state_scale
from kkl_bench.protocol.simulate import Trajectories, sha256_of_arrays
from kkl_bench.protocol.streams import PAPER_TRACK, draw_trajectory, root_seed, trajectory_rng
from kkl_bench.registry import did_you_mean, systems
from kkl_bench.suite.plants import simulate_plant, true_plant
from kkl_bench.suite.tracks import TaskDefinition, get_track


@dataclass(frozen=True)
class Task:
    """One benchmark cell: a system under one of a track's tasks (``regime`` names it).

    A task is resolved once, when it is made: its track's declaration of it
    (``definition``: regime, noise, x0 box, horizon, plant, measurement model) and whether
    the track fits estimators per task (``fitted_per_task``) are read from the track then
    and travel with the task through the run; nothing downstream looks the track up
    again. A task of a track this install does not declare, or at another version, or of
    a system the track does not cover, cannot be made (``TrackError``, ``ValueError``).
    """

    system: str
    regime: str
    version: int = PROTOCOL_VERSION
    track: str = PAPER_TRACK
    definition: TaskDefinition = field(init=False, repr=False, compare=False)
    fitted_per_task: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        track = get_track(self.track)
        if self.version != track.version:
            raise ValueError(f"task {self.id}: track {track.name!r} is at version {track.version}")
        if self.system not in track.systems:
            raise ValueError(
                f"task {self.id}: track {track.name!r} covers {', '.join(track.systems)}, "
                f"not {self.system!r}"
            )
        object.__setattr__(self, "definition", track.task(self.regime, self.system))
        object.__setattr__(self, "fitted_per_task", track.fitted_per_task)

    @property
    def id(self) -> str:
        prefix = "" if self.track == PAPER_TRACK else f"{self.track}/"
        return f"{prefix}{self.system}/{self.regime}@v{self.version}"

    def __str__(self) -> str:
        return self.id


@dataclass(frozen=True)
class Profile:
    """How many test trajectories a run scores and the training budgets it grants."""

    name: str
    description: str
    n_test: int
    budgets: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    smoke: bool = False
    """A smoke test of the pipeline: its numbers say nothing about the methods, and a
    board of it says so and compares nothing with the paper."""

    def budget_for(self, *tables: str) -> dict[str, Any]:
        """The default budget updated with each of ``tables`` that the profile has, in
        turn: the estimator's, then a variant's (``"kalmannet"``, then
        ``"kalmannet[gain_init='ekf']"``, its canonical name)."""
        budget = dict(self.budgets.get("default", {}))
        for table in tables:
            budget.update(self.budgets.get(table, {}))
        return budget


class ProfileError(ValueError):
    """A profile file is malformed or names no such profile."""


def load_profiles(text: str | None = None) -> dict[str, Profile]:
    """Parse profiles from TOML ``text`` (default: the built-in ``tasks/profiles.toml``)."""
    if text is None:
        text = importlib.resources.files("kkl_bench.tasks").joinpath("profiles.toml").read_text()
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ProfileError(f"profiles file is not valid TOML: {error}") from error
    profiles = {}
    for name, spec in table.items():
        if not isinstance(spec, dict):
            raise ProfileError(f"profile {name!r} must be a table, got {spec!r}")
        n_test = spec.get("n_test")
        if not isinstance(n_test, int) or isinstance(n_test, bool) or n_test < 1:
            raise ProfileError(
                f"profile {name!r}: n_test must be a positive integer, got {n_test!r}"
            )
        budgets = spec.get("budget", {})
        if not isinstance(budgets, dict) or not all(isinstance(b, dict) for b in budgets.values()):
            raise ProfileError(f"profile {name!r}: budget must hold one table per estimator")
        smoke = spec.get("smoke", False)
        if not isinstance(smoke, bool):
            raise ProfileError(f"profile {name!r}: smoke must be true or false, got {smoke!r}")
        profiles[name] = Profile(
            name=name,
            description=str(spec.get("description", "")),
            n_test=n_test,
            budgets=MappingProxyType({key: MappingProxyType(b) for key, b in budgets.items()}),
            smoke=smoke,
        )
    return profiles


def get_profile(name: str) -> Profile:
    """The built-in profile ``name``; the error lists the valid ones and suggests the
    closest."""
    profiles = load_profiles()
    if name not in profiles:
        raise ProfileError(
            f"unknown profile {name!r}; valid profiles: {', '.join(profiles)}"
            f"{did_you_mean(name, profiles)}"
        )
    return profiles[name]


@dataclass(frozen=True)
class TestSet:
    """The scored trajectories of one task.

    Attributes
    ----------
    task: the cell.
    data: the trajectories (``x`` is the truth an estimator never sees).
    regime_params: ``(n_test, k)`` each trajectory's regime parameters.
    state_scale: ``(n_x,)`` steady-state standard deviation of each state over the set.
    stream_fingerprint, fingerprint: see the module docstring.
    """

    __test__ = False  # not a pytest class

    task: Task
    data: Trajectories
    regime_params: np.ndarray
    state_scale: np.ndarray
    stream_fingerprint: str
    fingerprint: str


def make_test_set(task: Task, n_test: int) -> TestSet:
    """:func:`build_test_set`, cached in memory (its arrays are read-only)."""
    root_seed(task.system, task.regime, "test", task.track)  # refused if sealed
    return _cached_test_set(task, task.definition, n_test)


@dataclass(frozen=True)
class _Draws:
    """The random draws of a test set, stacked: ``x0: (n, n_x)``, ``r: (n, m)``,
    ``process_noise: (n, steps - 1, n_x)``, ``measurement_noise: (n, steps, n_y)``."""

    x0: np.ndarray
    r: np.ndarray
    process_noise: np.ndarray
    measurement_noise: np.ndarray

    def fingerprint(self) -> str:
        return sha256_of_arrays(self.x0, self.r, self.process_noise, self.measurement_noise)


def _draw(task: Task, n_test: int) -> _Draws:
    """The first ``n_test`` trajectories' draws of ``task``'s test stream, in the protocol's
    order: initial state from the task's box, the regime's uniform numbers, the process
    noise and the measurement noise (with the task's standard deviations)."""
    definition = task.definition
    system = systems.get(task.system)()
    low, high = definition.x0_box.for_system(system)
    n_numbers = definition.regime().n_numbers(DT * np.arange(definition.n_samples))
    root = root_seed(task.system, task.regime, "test", task.track)
    draws = [
        draw_trajectory(
            trajectory_rng(root, i),
            low,
            high,
            definition.n_samples,
            definition.sigma_w,
            definition.sigma_v,
            n_numbers,
            system.n_y,
            None if definition.measurement.noise.gaussian else definition.measurement.noise.sample,
        )
        for i in range(n_test)
    ]
    return _Draws(
        x0=np.stack([d.x0 for d in draws]),
        r=np.stack([d.r for d in draws]),
        process_noise=np.stack([d.process_noise for d in draws]),
        measurement_noise=np.stack([d.measurement_noise for d in draws]),
    )


def stream_fingerprint(task: Task, n_test: int) -> str:
    """The ``stream_fingerprint`` of ``task``'s first ``n_test`` test trajectories, without
    simulating them (what a stored cell's test set must match)."""
    return _stream_fingerprint(task, task.definition, n_test)


@functools.lru_cache(maxsize=256)
def _stream_fingerprint(task: Task, definition: TaskDefinition, n_test: int) -> str:
    """Cached by the task's definition too: a track read anew may define it differently."""
    return _draw(task, n_test).fingerprint()


def build_test_set(task: Task, n_test: int) -> TestSet:
    """Draw and simulate the first ``n_test`` trajectories of ``task``'s test stream.

    Trajectory ``i`` is the same whatever ``n_test`` is (draws: :func:`_draw`). The
    plant is the task's (:mod:`kkl_bench.suite.plants`): the nominal model but on ``mismatch``;
    so is the measurement model (:mod:`kkl_bench.measurement`): ``y`` is NaN at the
    samples it does not observe.
    """
    definition = task.definition
    system = true_plant(task.system, definition.plant, task.track)
    regime = definition.regime()
    draws = _draw(task, n_test)
    t = DT * np.arange(definition.n_samples)
    params = regime.params_from_uniform(draws.r)
    u = regime.signal(t, params)
    with np.errstate(over="ignore", invalid="ignore"):
        data = simulate_plant(
            system,
            definition.plant,
            draws.x0,
            u,
            draws.process_noise,
            draws.measurement_noise,
            definition.measurement,
        )
    escaped = np.flatnonzero(~np.isfinite(data.x).all(axis=(1, 2)))
    if escaped.size:
        raise ValueError(
            f"task {task.id}: the true state of test trajectories {escaped.tolist()} is not "
            "finite (it escapes to infinity); the track's x0 box or inputs leave the system's "
            "basin"
        )
    for array in (data.t, data.u, data.x, data.y, params):
        array.flags.writeable = False
    return TestSet(
        task=task,
        data=data,
        regime_params=params,
        state_scale=state_scale(data.x),
        stream_fingerprint=draws.fingerprint(),
        fingerprint=data.fingerprint(),
    )


@functools.lru_cache(maxsize=64)
def _cached_test_set(task: Task, definition: TaskDefinition, n_test: int) -> TestSet:
    return build_test_set(task, n_test)
