"""Online cost of every estimator, timed side by side in one run (``kkl-bench cost``).

A cell's ``estimate_us_per_step`` is the wall time of the run that scored it.
The cells of a leaderboard are scored by many runs (several commits and
sessions, one or two jobs on the machine), so those times do not compare
with one another. :func:`measure` times ``estimate`` again for every
(estimator, system, task) of a :class:`~kkl_bench.harness.RunSpec` in one
process, in turn, on the same test sets, with the trained models of the cache
(fitted if missing), on ``threads`` threads, best of ``rounds``. The EKF
(:data:`REFERENCE`) is always timed beside them, so every row carries the
reference's cost *from its own run*: a published ratio to the EKF never
compares times of two runs.

A measurement is merged into an existing file by (estimator, system, track,
regime): the rows it timed replace their namesakes, every other row keeps its
own run, commit and reference cost (``replace=True`` rewrites the file whole).

One thread is the default: it is what each worker of ``kkl-bench run --jobs 2``
has on two cores, and all the filters' Python loops use. The published cost
table reads the result (:data:`COST_FILE`) in place of the cells' own times.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Hashable
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from kkl_bench import variants
from kkl_bench.executors import thread_limit
from kkl_bench.results import provenance
from kkl_bench.scoring import timed_estimate, warm_up
from kkl_bench.spec import RunSpec, make_fit_context
from kkl_bench.task import make_test_set

COST_FILE = "cost.csv"
"""The measurement's file name in the leaderboard folder."""
REFERENCE = "ekf"
"""The estimator timed beside every measurement; rows compare with it."""
KEY = ["estimator", "system", "track", "regime"]
"""What identifies a row: a measurement replaces the stored rows of the keys it timed."""

COLUMNS = [
    "estimator",
    "system",
    "track",
    "regime",
    "trajectories",
    "us_per_trajectory_step",
    "rounds",
    "threads",
    "seed",
    "git_commit",
    "run",
    "reference_us_per_trajectory_step",
]
"""``run`` numbers the measurements merged into one file (1, 2, ...); the reference
column is :data:`REFERENCE`'s cost on the same test set in the same run."""


def fastest_round_robin(
    calls: dict[Hashable, Callable[[], object]],
    rounds: int = 3,
    threads: int = 1,
    max_seconds: float = 10.0,
    after_round: Callable[[dict[Hashable, float], dict[Hashable, int]], None] = lambda *_: None,
) -> tuple[dict[Hashable, float], dict[Hashable, int]]:
    """The fastest wall time (s) of each call and how many times it was timed.

    The calls are timed in turn, round after round, on ``threads`` threads, so a slow
    spell of the machine falls on all of them alike (callers warm them up first). A call
    stops being timed after ``rounds`` timings, or earlier once its timings add up to
    ``max_seconds`` (it is always timed once). ``after_round(best, counts)`` is called
    after each round (to save what is measured so far).
    """
    if rounds < 1 or threads < 1 or max_seconds <= 0:
        raise ValueError(
            f"rounds and threads must be at least 1 and max_seconds positive; got rounds="
            f"{rounds}, threads={threads}, max_seconds={max_seconds}"
        )
    best: dict[Hashable, float] = {}
    counts = dict.fromkeys(calls, 0)
    spent = dict.fromkeys(calls, 0.0)
    with thread_limit(threads):
        for round_ in range(rounds):
            due = [key for key in calls if counts[key] == 0 or spent[key] < max_seconds]
            if not due:
                break
            for key in tqdm(due, desc=f"timing, round {round_ + 1}/{rounds}", unit="call"):
                start = time.perf_counter()
                calls[key]()
                seconds = time.perf_counter() - start
                best[key] = min(best.get(key, math.inf), seconds)
                counts[key] += 1
                spent[key] += seconds
            after_round(best, counts)
    return best, counts


def measure(
    spec: RunSpec,
    out: Path,
    rounds: int = 3,
    threads: int = 1,
    max_seconds: float = 10.0,
    replace: bool = False,
) -> pd.DataFrame:
    """Time ``estimate`` of every estimator of ``spec``, and of :data:`REFERENCE` beside
    them, on the test set of every task of ``spec`` (:func:`fastest_round_robin`), and
    merge one row per (estimator, system, task) into ``out`` (CSV, :data:`COLUMNS`).

    The reference's own rows enter ``out`` only if ``spec`` asks for it. Each estimator
    is fitted once per system with the first seed it runs with (from the cache when it
    holds the model). ``out`` is written after every round: an interrupted run keeps what
    it measured. ``replace`` drops the rows stored before. Returns this run's rows.
    """
    commit = provenance()["git_commit"]  # the code that runs, read before anything is loaded
    stored = None if replace else read_costs(out)
    run = 1 if stored is None or stored.empty else int(stored["run"].max()) + 1
    timed = list(dict.fromkeys([*spec.estimators, REFERENCE]))
    fitted, test_sets = {}, {}
    for name, system in tqdm(
        [(name, system) for name in timed for system in spec.systems],
        desc="loading fitted models",
        unit="model",
    ):
        context = make_fit_context(spec, name, system, spec.seeds_for(name)[0])
        fitted[name, system] = variants.build(name).fit(context)
        for task in spec.tasks(system):
            test_sets.setdefault(task, make_test_set(task, spec.profile.n_test).data)
    calls = {
        (name, task): functools.partial(timed_estimate, fitted[name, task.system], data)
        for name in timed
        for task, data in test_sets.items()
    }
    with thread_limit(threads):
        for name, task in calls:
            warm_up(fitted[name, task.system], test_sets[task])

    def rows(best: dict, counts: dict) -> pd.DataFrame:
        return pd.DataFrame(
            [
                {
                    "estimator": name,
                    "system": task.system,
                    "track": task.track,
                    "regime": task.regime,
                    "trajectories": test_sets[task].y.shape[0],
                    "us_per_trajectory_step": _per_step(seconds, test_sets[task]),
                    "rounds": counts[name, task],
                    "threads": threads,
                    "seed": spec.seeds_for(name)[0],
                    "git_commit": commit,
                    "run": run,
                    "reference_us_per_trajectory_step": _per_step(
                        best.get((REFERENCE, task), math.nan), test_sets[task]
                    ),
                }
                for (name, task), seconds in best.items()
                if name in spec.estimators
            ],
            columns=COLUMNS,
        )

    def save(best: dict, counts: dict) -> None:
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = out.with_name(out.name + ".partial")
        merge(stored, rows(best, counts)).to_csv(partial, index=False, float_format="%.6g")
        os.replace(partial, out)

    best, counts = fastest_round_robin(calls, rounds, threads, max_seconds, save)
    return rows(best, counts)


def _per_step(seconds: float, data) -> float:
    """µs per trajectory-step of a call that took ``seconds`` on ``data``."""
    return 1e6 * seconds / data.y[..., 0].size


def merge(stored: pd.DataFrame | None, new: pd.DataFrame) -> pd.DataFrame:
    """``stored`` rows whose key (:data:`KEY`) ``new`` lacks, then ``new``'s rows."""
    if stored is None or stored.empty:
        return new.reset_index(drop=True)
    timed = pd.MultiIndex.from_frame(new[KEY])
    kept = stored[~pd.MultiIndex.from_frame(stored[KEY]).isin(timed)]
    return pd.concat([kept, new], ignore_index=True)[COLUMNS]


def read_costs(path: Path) -> pd.DataFrame | None:
    """The rows :func:`measure` wrote to ``path``, or None if there is no such file.

    A file written before measurements were merged (no ``run`` column) was one run: its
    rows get run 1 and the reference's cost from its own :data:`REFERENCE` rows. Raises
    ``ValueError`` naming the file and the missing columns if it is not a measurement.
    """
    if not path.exists():
        return None
    costs = pd.read_csv(path)
    merged_since = ["run", "reference_us_per_trajectory_step"]
    needed = COLUMNS if "run" in costs.columns else [c for c in COLUMNS if c not in merged_since]
    missing = [column for column in needed if column not in costs.columns]
    if missing:
        raise ValueError(
            f"{path} is not a `kkl-bench cost` measurement: no column(s) {', '.join(missing)}"
        )
    if "run" not in costs.columns:
        reference = costs.loc[
            costs["estimator"] == REFERENCE, [*KEY[1:], "us_per_trajectory_step"]
        ].rename(columns={"us_per_trajectory_step": "reference_us_per_trajectory_step"})
        costs = costs.assign(run=1).merge(reference, on=KEY[1:], how="left")
    return costs


def with_measured_costs(summary: pd.DataFrame, costs: pd.DataFrame) -> pd.DataFrame:
    """``summary`` (one row per estimator, system and regime) with ``estimate_us_per_step``
    taken from ``costs`` where they have a row for it (an estimator's online cost does not
    depend on its training seed); the rows ``costs`` lack keep the cells' own times."""
    measured = costs.set_index(["estimator", "system", "regime"])["us_per_trajectory_step"]
    keys = pd.MultiIndex.from_frame(summary[["estimator", "system", "regime"]])
    replaced = measured.reindex(keys).to_numpy()
    summary = summary.copy()
    summary["estimate_us_per_step"] = summary["estimate_us_per_step"].where(
        pd.isna(replaced), replaced
    )
    return summary
