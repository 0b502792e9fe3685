"""Online cost of every estimator, timed side by side in one run (``kkl-bench cost``).

A cell's ``estimate_us_per_step`` is the wall time of the run that scored it.
The cells of a leaderboard are scored by many runs (several commits and
sessions, one or two jobs on the machine), so those times do not compare
with one another. :func:`measure` times ``estimate`` again for every
(estimator, system, task) of a :class:`~kkl_bench.run.harness.RunSpec` in one
process, in turn, on the same test sets, with the trained models of the cache
(fitted if missing), on ``threads`` threads, best of ``rounds``. The EKF
(:data:`REFERENCE`) is always timed beside them, so every row carries the
reference's cost *from its own run*: a published ratio to the EKF never
compares times of two runs.

A measurement is merged into an existing file by (estimator, system, track,
regime): the rows it timed replace their namesakes, every other row keeps its
own run, commit and reference cost (``replace=True`` rewrites the file whole).

One thread is the default: it is what each worker of ``kkl-bench run --jobs 2``
has on two cores. The published cost table reads the result (:data:`COST_FILE`) in
place of the cells' own times.

A row's cost is its algorithm's, not its Python loop's (protocol 6.3): a model-based row
with engines (``engine=`` of ``ekf`` and ``ukf``) is timed on its compiled engine, and
its reference engine (filterpy) is timed beside it in the same run. Every row also
carries its arithmetic: the flops of one trajectory-step (the filters' own count,
``flops_per_step()``; a network's matrix products by its layer sizes,
:func:`counted_flops`), this machine's peak in the row's precision measured in the same
run (:func:`peak_gflops`), the floor they imply, and the row's cost over that floor.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Hashable
from pathlib import Path

import numba
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from kkl_bench import families, variants
from kkl_bench.estimator import Estimator
from kkl_bench.registry import estimators
from kkl_bench.run.scoring import timed_estimate, warm_up
from kkl_bench.run.spec import RunSpec, fit_groups, make_fit_context
from kkl_bench.suite.task import Task, make_test_set
from kkl_bench.support import flops
from kkl_bench.support.executors import thread_limit
from kkl_bench.support.provenance import provenance

COST_FILE = "cost.csv"
"""The measurement's file name in the leaderboard folder."""
REFERENCE = "ekf"
"""The estimator timed beside every measurement; rows compare with it."""
KEY = ["estimator", "system", "track", "regime"]
"""What identifies a row: a measurement replaces the stored rows of the keys it timed."""

COLUMNS = [
    "estimator",
    "family",
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
    "engine",
    "reference_engine_us_per_trajectory_step",
    "flops_per_trajectory_step",
    "precision",
    "peak_gflops",
    "floor_us_per_trajectory_step",
    "over_floor",
    "normals_per_trajectory_step",
    "uniforms_per_trajectory_step",
    "transcendentals_per_trajectory_step",
    "normal_ns",
    "uniform_ns",
    "transcendental_ns",
]
"""``run`` numbers the measurements merged into one file (1, 2, ...); the reference
column is :data:`REFERENCE`'s cost on the same test set in the same run. ``engine`` is
the engine timed (``compiled`` or ``reference`` for a model-based row with engines,
``numpy`` for one without, ``torch`` for a network), and
``reference_engine_us_per_trajectory_step`` the reference engine's cost beside a
compiled one. ``floor = flops / peak + normals normal_ns + uniforms uniform_ns +
transcendentals transcendental_ns``, at the measured ``peak_gflops`` in the row's
``precision`` and the measured cost of one operation of each kind
(:func:`operation_ns`); ``over_floor`` is the cost over it. The counts are the row's own
(``operations_per_step()``; zero for a row that declares none)."""

ARITHMETIC = COLUMNS[COLUMNS.index("engine") :]
"""The columns measured since engines and floors were (issue 41; the operation counts
and costs since issue 65)."""
OPERATIONS = ("normal", "uniform", "transcendental")
"""What a floor counts besides flops: standard normal and uniform draws and
transcendental functions (:func:`operation_ns`)."""
OPERATION_SIZE = 2**16
"""Operations of each kind per timed call of :func:`operation_ns`."""
ENGINES = ("compiled", "reference")
"""A model-based row with an ``engine`` hyperparameter is timed on both."""
PEAK_SIZE = 1024
"""The square matrix product whose best time gives the peak (:func:`peak_gflops`)."""


def fastest_round_robin(
    calls: dict[Hashable, Callable[[], object]],
    rounds: int = 3,
    threads: int = 1,
    max_seconds: float = 10.0,
    after_round: Callable[[dict[Hashable, float], dict[Hashable, int]], None] = lambda *_: None,
    group: Callable[[Hashable], Hashable] | None = None,
) -> tuple[dict[Hashable, float], dict[Hashable, int]]:
    """The fastest wall time (s) of each call and how many times it was timed.

    The calls are timed in turn, round after round, on ``threads`` threads, so a slow
    spell of the machine falls on all of them alike (callers warm them up first). A call
    stops being timed after ``rounds`` timings, or earlier once its timings add up to
    ``max_seconds`` (it is always timed once). ``after_round(best, counts)`` is called
    after each round (to save what is measured so far).

    With ``group`` (``group(key)``: the calls of one estimator, say, which follow one
    another), the first call of each group in a round runs once untimed before it is
    timed. The first call after another group's finds the caches holding the other's code
    and data: the compiled EKF on Duffing's 20 test trajectories (0.4 ms a call) took 29 ns a
    trajectory-step right after a ``kalmannet`` estimate and 19 right after itself
    (protocol 6.3).
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
            previous = object()  # no group yet
            for key in tqdm(due, desc=f"timing, round {round_ + 1}/{rounds}", unit="call"):
                if group is not None and group(key) != previous:
                    calls[key]()  # untimed: the group's code and data into the caches
                    previous = group(key)
                start = time.perf_counter()
                calls[key]()
                seconds = time.perf_counter() - start
                best[key] = min(best.get(key, math.inf), seconds)
                counts[key] += 1
                spent[key] += seconds
            after_round(best, counts)
    return best, counts


def peak_gflops(precision: str, threads: int = 1, rounds: int = 5, device: str = "cpu") -> float:
    """This machine's peak, GFLOP/s: the best of ``rounds`` products of two
    :data:`PEAK_SIZE` square matrices on ``threads`` threads (numpy's BLAS for
    ``float64``, torch for ``float32``; ``2 N^3`` flops each), or on the GPU where
    ``device`` is ``cuda`` (``float32`` only, each product waited for)."""
    valid = ("float32", "float64") if device == "cpu" else ("float32",)
    if precision not in valid:
        raise ValueError(f"precision {precision!r} on {device}; valid: {', '.join(valid)}")
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, PEAK_SIZE, PEAK_SIZE))
    multiply = np.matmul
    if precision == "float32":
        a, b = (torch.from_numpy(m).float().to(device) for m in (a, b))
        multiply = torch.mm
    wait = torch.cuda.synchronize if device == "cuda" else lambda: None
    best = math.inf
    with thread_limit(threads):
        for _ in range(rounds + 1):  # the first is a warm-up
            start = time.perf_counter()
            multiply(a, b)
            wait()
            best = min(best, time.perf_counter() - start)
    return 2 * PEAK_SIZE**3 / best / 1e9


@numba.njit(cache=True)
def _draw_normals(rng, out):
    for i in range(out.shape[0]):
        out[i] = rng.standard_normal()


@numba.njit(cache=True)
def _draw_uniforms(rng, out):
    for i in range(out.shape[0]):
        out[i] = rng.random()


@numba.njit(cache=True)
def _exponentials(values, out):
    for i in range(values.shape[0]):
        out[i] = math.exp(values[i])


def operation_ns(rounds: int = 5) -> dict[str, float]:
    """This machine's cost, ns, of one operation of each of :data:`OPERATIONS`, the best
    of ``rounds`` calls of :data:`OPERATION_SIZE` each, as the compiled filters run them:
    a standard normal and a uniform number drawn inside a numba loop from a
    ``numpy.random.Generator`` (numpy's algorithms on PCG64, what the particle filter's
    and the EnKF's kernels draw), and ``math.exp`` of an array in a numba loop (the
    transcendental a particle's weight needs)."""
    rng = np.random.default_rng(0)
    values, out = rng.uniform(-5.0, 0.0, OPERATION_SIZE), np.empty(OPERATION_SIZE)
    calls = {
        "normal": lambda: _draw_normals(rng, out),
        "uniform": lambda: _draw_uniforms(rng, out),
        "transcendental": lambda: _exponentials(values, out),
    }
    costs = {}
    for kind, call in calls.items():
        best = math.inf
        for _ in range(rounds + 1):  # the first compiles or loads, and warms up
            start = time.perf_counter()
            call()
            best = min(best, time.perf_counter() - start)
        costs[kind] = 1e9 * best / OPERATION_SIZE
    return costs


def counted_operations(estimator) -> dict[str, float]:
    """``{kind: count}`` of :data:`OPERATIONS` one trajectory-step of a fitted estimator
    must do besides its flops: its own ``operations_per_step()``, zero where it declares
    none."""
    declared = getattr(estimator, "operations_per_step", None)
    counts = declared() if declared is not None else {}
    return {kind: float(counts.get(kind, 0)) for kind in OPERATIONS}


def floor_us(flops_count: float, peak: float, counts: dict, unit_ns: dict) -> float:
    """A row's floor, µs per trajectory-step: ``flops_count`` at ``peak`` GFLOP/s plus the
    ``counts`` of :data:`OPERATIONS` at their costs ``unit_ns``."""
    return flops_count / (peak * 1e3) + sum(counts[k] * unit_ns[k] for k in OPERATIONS) / 1e3


def counted_flops(estimator, data) -> tuple[float, str]:
    """``(flops per trajectory-step, precision)`` of a fitted estimator on the test set
    ``data``: its own ``flops_per_step()`` where it declares one (the filters, in
    float64), else the matrix products one ``estimate`` on ``data`` runs, counted by the
    layer sizes (:func:`kkl_bench.support.flops.counted`; a network, in float32); NaN where
    that counts nothing (a plugin computing outside torch: its floor is unknown)."""
    declared = getattr(estimator, "flops_per_step", None)
    if declared is not None:
        return declared(), "float64"
    total = flops.counted(lambda: estimator.estimate(data.t, data.y, data.u))
    # nothing counted: a plugin whose arithmetic runs outside torch and declares none
    return (total / data.y[..., 0].size if total else math.nan), "float32"


def timed_variants(name: str) -> dict[str, str]:
    """``{engine: variant}`` to time for row ``name``: both :data:`ENGINES` of an
    estimator with an ``engine`` hyperparameter, the row itself otherwise (its engine
    ``torch`` for a network, ``numpy`` for a filter without engines)."""
    base, params = variants.parse(name)
    estimator = estimators.get(base)
    if "engine" in estimator.param_names():
        return {
            engine: variants.canonical(
                f"{base}[{','.join(f'{k}={v!r}' for k, v in {**params, 'engine': engine}.items())}]"
            )
            for engine in ENGINES
        }
    return {"numpy" if getattr(estimator, "flops_per_step", None) else "torch": name}


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

    The reference's own rows enter ``out`` only if ``spec`` asks for it; beside other
    rows it is timed on the engine its column reads (its compiled one). Each estimator
    is fitted as a run fits it (:func:`fitted_for_tasks`: once per system, or once per
    measurement model on a track fitted per task) with the first seed it runs with (from
    the cache when it holds the model). ``out`` is written after every round: an
    interrupted run keeps what it measured. ``replace`` drops the rows stored before.
    Returns this run's rows.
    """
    commit = provenance()["git_commit"]  # the code that runs, read before anything is loaded
    stored = None if replace else read_costs(out)
    run = 1 if stored is None or stored.empty else int(stored["run"].max()) + 1
    engines = {name: timed_variants(name) for name in spec.estimators}
    if REFERENCE not in engines:  # beside the rows, only the engine its column reads
        engines[REFERENCE] = dict(list(timed_variants(REFERENCE).items())[:1])
    timed = list(engines)
    fitted, test_sets = {}, {}
    for name, system in tqdm(
        [(name, system) for name in timed for system in spec.systems],
        desc="loading fitted models",
        unit="model",
    ):
        for engine, variant in engines[name].items():
            for task, model in fitted_for_tasks(spec, variant, system, name).items():
                fitted[name, engine, task] = model
        for task in spec.tasks(system):
            test_sets.setdefault(task, make_test_set(task, spec.profile.n_test).data)
    calls = {
        (name, engine, task): functools.partial(timed_estimate, fitted[name, engine, task], data)
        for name in timed
        for engine in engines[name]
        for task, data in test_sets.items()
    }
    with thread_limit(threads):
        for name, engine, task in calls:
            warm_up(fitted[name, engine, task], test_sets[task])
    row_engine = {name: next(iter(engines[name])) for name in timed}  # compiled if any
    arithmetic = {
        (name, task): counted_flops(fitted[name, row_engine[name], task], test_sets[task])
        for name in tqdm(spec.estimators, desc="counting flops", unit="row")
        for task in test_sets
    }
    operations = {
        (name, task): counted_operations(fitted[name, row_engine[name], task])
        for name in spec.estimators
        for task in test_sets
    }
    peaks = {
        precision: peak_gflops(precision, threads)
        for precision in sorted({precision for _, precision in arithmetic.values()})
    }
    with thread_limit(threads):
        unit_ns = operation_ns()

    def rows(best: dict, counts: dict) -> pd.DataFrame:
        measured = []
        for (name, engine, task), seconds in best.items():
            if name not in spec.estimators or engine != row_engine[name]:
                continue
            data = test_sets[task]
            arithmetic_flops, precision = arithmetic[name, task]
            operation_counts = operations[name, task]
            floor = floor_us(arithmetic_flops, peaks[precision], operation_counts, unit_ns)
            cost = _per_step(seconds, data)
            reference_engine = best.get((name, "reference", task), math.nan)
            measured.append(
                {
                    "estimator": name,
                    "family": families.row_family(name),
                    "system": task.system,
                    "track": task.track,
                    "regime": task.regime,
                    "trajectories": data.y.shape[0],
                    "us_per_trajectory_step": cost,
                    "rounds": counts[name, engine, task],
                    "threads": threads,
                    "seed": spec.seeds_for(name)[0],
                    "git_commit": commit,
                    "run": run,
                    "reference_us_per_trajectory_step": _per_step(
                        best.get((REFERENCE, row_engine[REFERENCE], task), math.nan), data
                    ),
                    "engine": getattr(fitted[name, engine, task], "engine_used", engine),
                    "reference_engine_us_per_trajectory_step": (
                        _per_step(reference_engine, data) if engine == "compiled" else math.nan
                    ),
                    "flops_per_trajectory_step": arithmetic_flops,
                    "precision": precision,
                    "peak_gflops": peaks[precision],
                    "floor_us_per_trajectory_step": floor,
                    "over_floor": cost / floor,
                    **{
                        f"{kind}s_per_trajectory_step": operation_counts[kind]
                        for kind in OPERATIONS
                    },
                    **{f"{kind}_ns": unit_ns[kind] for kind in OPERATIONS},
                }
            )
        return pd.DataFrame(measured, columns=COLUMNS)

    def save(best: dict, counts: dict) -> None:
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = out.with_name(out.name + ".partial")
        merge(stored, rows(best, counts)).to_csv(partial, index=False, float_format="%.6g")
        os.replace(partial, out)

    best, counts = fastest_round_robin(
        calls, rounds, threads, max_seconds, save, group=lambda key: key[:2]
    )
    return rows(best, counts)


def fitted_for_tasks(spec: RunSpec, variant: str, system: str, row: str) -> dict[Task, Estimator]:
    """``variant`` fitted for each task of ``spec`` on ``system`` as a run fits it (once per
    group of :func:`~kkl_bench.run.spec.fit_groups`: on a track fitted per measurement
    model, with that model's conditions), with the first seed ``row`` runs with."""
    seed = spec.seeds_for(row)[0]
    fitted = {}
    for conditions, tasks in fit_groups(spec.tasks(system)):
        context = make_fit_context(spec, variant, system, seed, conditions=conditions)
        model = variants.build(variant).fit(context)
        fitted.update(dict.fromkeys(tasks, model))
    return fitted


def _per_step(seconds: float, data) -> float:
    """µs per trajectory-step of a call that took ``seconds`` on ``data``."""
    return 1e6 * seconds / data.y[..., 0].size


def merge(stored: pd.DataFrame | None, new: pd.DataFrame) -> pd.DataFrame:
    """``stored`` rows whose key (:data:`KEY`) ``new`` lacks, then ``new``'s rows."""
    if stored is None or stored.empty:
        return new.reset_index(drop=True)
    timed = pd.MultiIndex.from_frame(new[KEY])
    kept = stored[~pd.MultiIndex.from_frame(stored[KEY]).isin(timed)]
    return pd.concat([kept, new], ignore_index=True).reindex(columns=COLUMNS)


def read_costs(path: Path) -> pd.DataFrame | None:
    """The rows :func:`measure` wrote to ``path``, or None if there is no such file.

    A file written before families were recorded gets each row's declared family
    (:mod:`kkl_bench.families`). A file written before measurements were merged (no
    ``run`` column) was one run: its
    rows get run 1 and the reference's cost from its own :data:`REFERENCE` rows; one
    written before engines and floors were measured (no :data:`ARITHMETIC` columns) has
    them empty. Raises ``ValueError`` naming the file and the missing columns if it is not
    a measurement.
    """
    if not path.exists():
        return None
    costs = pd.read_csv(path)
    if "family" not in costs.columns and "estimator" in costs.columns:  # before families
        costs.insert(1, "family", costs["estimator"].map(families.row_family))
    for column in ARITHMETIC:
        if column not in costs.columns:
            costs[column] = math.nan
    for column in ("engine", "precision"):  # text, empty in rows measured before them
        costs[column] = costs[column].astype(object)
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
