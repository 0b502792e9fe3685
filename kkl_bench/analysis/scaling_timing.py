"""The scaling study's online costs: every fitted estimator of every Lorenz-96 size loaded
(from the cache, or untrained at the trained models' sizes) and timed side by side in one
run, round-robin on one thread, beside the reference EKF of the same run; stored timings
merged with new ones (:mod:`kkl_bench.analysis.scaling` reads them into the study)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from kkl_bench import families, variants
from kkl_bench.analysis.cost import fastest_round_robin, timed_variants
from kkl_bench.analysis.scaling import (
    BATCHES,
    ENGINE_ONLINE,
    MODELS,
    ONLINE,
    REFERENCE,
    REFERENCE_ONLINE,
    REGIME,
    STEPS,
    TIMING_COLUMNS,
    TRACK,
    system_name,
)
from kkl_bench.estimator import Estimator
from kkl_bench.kkl.optimize import probing
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import Task, make_test_set


def time_estimators(
    spec: RunSpec, fitted: dict[tuple[str, int], dict[str, Estimator]], repeats: int = 3
) -> pd.DataFrame:
    """Online cost of each fitted ``(estimator, n)`` on each of its engines
    (:func:`fit_from_cache`), timed round-robin on one thread.

    Returns columns estimator, n, engine (the key of ``fitted``'s engines), engine_used
    (what ran: ``reference`` where a system has no compiled model), batch, us_per_step
    (fastest of ``repeats``).
    """
    inputs = {}
    for n in {n for _, n in fitted}:
        data = make_test_set(Task(system_name(n), REGIME, 1, TRACK), spec.profile.n_test).data
        rows = {batch: np.arange(batch) % len(data.y) for batch in BATCHES}
        inputs[n] = {
            batch: (data.t[:STEPS], data.y[rows[batch], :STEPS], data.u[rows[batch], :STEPS])
            for batch in BATCHES
        }
    calls = {
        (name, n, engine, batch): _estimate_call(estimator, *inputs[n][batch])
        for (name, n), engines in fitted.items()
        for engine, estimator in engines.items()
        for batch in BATCHES
    }
    seconds, _ = fastest_round_robin(
        calls, rounds=repeats, max_seconds=math.inf, group=lambda key: key[:3]
    )
    return pd.DataFrame(
        [
            {
                "estimator": name,
                "n": n,
                "engine": engine,
                "engine_used": getattr(fitted[name, n][engine], "engine_used", engine),
                "batch": batch,
                "us_per_step": value * 1e6 / (batch * STEPS),
            }
            for (name, n, engine, batch), value in seconds.items()
        ]
    )


def _estimate_call(estimator: Estimator, t, y, u):
    """``estimator.estimate`` on fresh copies of ``y`` and ``u`` at every call."""
    return lambda: estimator.estimate(t, y.copy(), u.copy())


def fit_from_cache(spec: RunSpec, estimator: str, n: int, seed: int) -> dict[str, Estimator]:
    """``estimator`` fitted for Lorenz-96 with ``n`` states (loaded from the run's cache), on
    each engine it is timed on (:func:`kkl_bench.analysis.cost.timed_variants`: a filter with
    engines on its compiled engine and its reference engine beside it, as ``kkl-bench
    cost`` times it)."""
    system = system_name(n)
    return {
        engine: variants.build(variant).fit(make_fit_context(spec, variant, system, seed))
        for engine, variant in timed_variants(estimator).items()
    }


UNTRAINED_STEPS = 1
"""Optimizer steps (beyond :func:`~kkl_bench.kkl.optimize.probing`'s two) of every training
of an untrained model (:func:`fit_untrained`)."""


def fit_untrained(
    spec: RunSpec, estimator: str, n: int, seed: int, report: dict
) -> dict[str, Estimator]:
    """``estimator`` built for Lorenz-96 with ``n`` states at the profile's sizes with every
    training cut short (:data:`UNTRAINED_STEPS`, in ``spec``'s cache, which must be a
    temporary one), then given the choices its published fit made from data (``report``,
    :meth:`~kkl_bench.estimator.Estimator.adopt_choices`): the trained model's arithmetic
    without its weights, for timing only, on each engine of :func:`fit_from_cache`. A
    filter trains nothing and is fitted as usual."""
    with probing(UNTRAINED_STEPS):
        engines = fit_from_cache(spec, estimator, n, seed)
    for fitted in engines.values():
        fitted.adopt_choices(report)
    return engines


def published_report(results: pd.DataFrame, estimator: str, n: int, seed: int) -> dict:
    """The fit report of ``estimator``'s cells at ``n`` and ``seed`` on the track (every
    regime's cell keeps its fit's); empty if none holds one."""
    cells = results[
        (results.get("track") == TRACK)
        & (results["estimator"] == estimator)
        & (results["system"] == system_name(n))
        & (results["seed"] == seed)
    ]
    reports = [report for report in cells.get("fit_report", ()) if isinstance(report, dict)]
    return reports[0] if reports else {}


def _beside_reference(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` (estimator, n and :data:`ONLINE`, all from one timing run) with the
    reference's costs at each row's size as :data:`REFERENCE_ONLINE`."""
    reference = frame.loc[frame["estimator"] == REFERENCE, ["n", *ONLINE]]
    reference.columns = ["n", *REFERENCE_ONLINE]
    return frame.merge(reference, on="n", how="left")


def timing_frame(
    timings: pd.DataFrame, commit: str | None = None, models: str = MODELS[0]
) -> pd.DataFrame:
    """:func:`time_estimators`' long frame as one row per (estimator, n) with
    :data:`TIMING_COLUMNS`: a row timed on both engines is its compiled engine's, with its
    reference engine's costs beside (:data:`ENGINE_ONLINE`); the reference's costs are
    those it was timed at in this run (its compiled engine's), ``commit`` the code's
    (:func:`kkl_bench.support.provenance.provenance`), ``models`` what was timed (:data:`MODELS`).
    The run is numbered 1 until
    :func:`add_timings` places it after a stored study's."""
    wide = timings.pivot_table(
        index=["estimator", "n", "engine", "engine_used"], columns="batch", values="us_per_step"
    )
    wide.columns = [f"us_per_step_batch{batch}" for batch in wide.columns]
    wide = wide.reset_index()
    compiled = wide["engine"] == "compiled"
    beside = compiled.groupby([wide["estimator"], wide["n"]]).transform("any")  # two engines
    engines = wide[beside & (wide["engine"] == "reference")][["estimator", "n", *ONLINE]]
    engines.columns = ["estimator", "n", *ENGINE_ONLINE]
    rows = wide[~beside | compiled].drop(columns="engine")
    frame = rows.rename(columns={"engine_used": "engine"}).merge(
        engines, on=["estimator", "n"], how="left"
    )
    frame = _beside_reference(frame).assign(timing_run=1, timing_commit=commit)
    return _with_models(frame, models)[["estimator", "n", *TIMING_COLUMNS]]


def _with_models(frame: pd.DataFrame, models: str | pd.Series) -> pd.DataFrame:
    """``frame`` with its ``models`` column: ``models`` (:data:`MODELS`) for a learned row,
    empty for a row that trains nothing (a filter has no models to time)."""
    learned = families.of_rows(frame) == "learned"
    return frame.assign(
        models=pd.Series(models, index=frame.index).where(learned, "").astype(object)
    )


def stored_timings(study: Path | None) -> pd.DataFrame:
    """The timings of the study written to ``study`` (a ``scaling.csv``), one row per
    (estimator, n) timed; empty if there is none (or ``study`` is None)."""
    if study is None or not study.exists():
        return pd.DataFrame(columns=["estimator", "n", *TIMING_COLUMNS])
    frame = pd.read_csv(study, dtype={"timing_commit": str})  # a hash may read as a number
    frame = frame[frame[list(ONLINE)].notna().any(axis=1)]
    if "timing_run" not in frame:  # written before studies recorded their timing runs
        frame = _beside_reference(frame).assign(timing_run=1, timing_commit=None)
    for column in ("engine", *ENGINE_ONLINE):  # written before studies timed two engines
        if column not in frame:
            frame[column] = math.nan
    if "models" not in frame:  # written when every study timed the cache's trained models
        frame["models"] = MODELS[0]
    frame = _with_models(frame, frame["models"])
    frame["engine"] = frame["engine"].astype(object)
    return frame[["estimator", "n", *TIMING_COLUMNS]].reset_index(drop=True)


def untimed(cells: pd.DataFrame, stored: pd.DataFrame) -> list[tuple[str, int]]:
    """The ``(estimator, n)`` of ``cells`` that fitted and have no timing in ``stored``, and
    the reference at each of their sizes (it is timed in every run that times anything)."""
    timed = set(zip(stored["estimator"], stored["n"], strict=True))
    ok = cells[cells["status"] == "ok"]
    missing = [
        (estimator, int(n))
        for estimator, n in zip(ok["estimator"], ok["n"], strict=True)
        if (estimator, n) not in timed
    ]
    references = {(REFERENCE, n) for _, n in missing} - set(missing)
    return sorted(missing + sorted(references))


def add_timings(stored: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """``stored``'s rows, and ``new``'s (a later run, numbered after ``stored``'s) for
    every (estimator, n) ``stored`` lacks; the reference's new rows serve only as their run's
    comparison and do not replace its stored ones."""
    run = int(stored["timing_run"].max()) + 1 if len(stored) else 1
    timed = set(zip(stored["estimator"], stored["n"], strict=True))
    added = new[[key not in timed for key in zip(new["estimator"], new["n"], strict=True)]]
    frames = [frame for frame in (stored, added.assign(timing_run=run)) if len(frame)]
    return pd.concat(frames, ignore_index=True)
