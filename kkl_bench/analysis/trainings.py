"""How the learned rows' trainings ended (protocol 6.5), read from the fit reports of
stored cells, and how a refit moved a row's error (``kkl-bench trainings``).

Every training of a learned row records in its fit report the steps it ran, why it
stopped (``plateau``, ``cap`` or ``diverged``; nothing for a training from before the
plateau rule) and the step whose state it kept (:mod:`kkl_bench.support.convergence`
finds them), and in ``spent`` the steps, samples and seconds of each of its phases. The
cells a fit scored share its report, so a fit is counted once: by row, system, seed and
the report itself.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pandas as pd

from kkl_bench.analysis.summary import REGIME_TITLES, in_paper_order
from kkl_bench.run.results import recorded_seconds, records_processor_time
from kkl_bench.support.convergence import (
    DIVERGED,
    NO,
    STOPPED_BY,
    UNRECORDED,
    UNTRAINED,
    YES,
    outcome,
    trained,
    trainings,
    verdict,
)

UNRECORDED_STOP = "not recorded"
"""Why a training stopped, for one from before the plateau rule (its report says not)."""
STOPS = (*STOPPED_BY, UNRECORDED_STOP)

TRAINING_COLUMNS = [
    "estimator",
    "system",
    "seed",
    "training",
    "steps",
    "stopped",
    "best_step",
    "halvings",
    "last_halving",
    "diverged",
]


def training_records(cells: pd.DataFrame) -> pd.DataFrame:
    """One row per training of each distinct fit behind ``cells`` (the rows of
    :func:`~kkl_bench.run.results.load_results`): ``estimator``, ``system``, ``seed``,
    ``training`` (its path in the fit report, such as ``phase1_log.decoder``),
    ``steps``, ``stopped`` (:data:`STOPS`), ``best_step``, the step of the state kept,
    ``halvings`` and ``last_halving``, how many times the plateau rule halved its learning
    rate and at which step it last did (NaN where it never did), and ``diverged``, why the
    training diverged (:func:`divergence`; empty if it did not). A training from before
    the plateau rule records neither its steps nor a best step nor halvings (NaN): its
    steps are read as its curve's last measurement's, and it kept its last step
    (protocol 6.5)."""
    records = []
    for cell, report in distinct_fits(cells):
        if not trained(report):
            continue
        for path, training in trainings(report):
            curve = training["validation_curve"]
            steps = training.get("steps", curve[-1][0] if curve else np.nan)
            halved_at = training.get("lr_reductions")
            records.append(
                {
                    "estimator": cell.estimator,
                    "system": cell.system,
                    "seed": cell.seed,
                    "training": path,
                    "steps": steps,
                    "stopped": training.get("stopped", UNRECORDED_STOP),
                    "best_step": training.get(
                        "best_step", np.nan if "stopped" in training else steps
                    ),
                    "halvings": np.nan if halved_at is None else len(halved_at),
                    "last_halving": halved_at[-1] if halved_at else np.nan,
                    "diverged": divergence(training),
                }
            )
    return pd.DataFrame(records, columns=TRAINING_COLUMNS)


def distinct_fits(cells: pd.DataFrame) -> Iterator[tuple[Any, dict]]:
    """Each distinct fit behind ``cells`` once, as its first cell and its fit report: the
    cells a fit scored share its report, so a fit is known by its row, system, seed and
    the report itself. Cells without a report are skipped."""
    seen = set()
    for cell in cells.itertuples(index=False):
        report = cell.fit_report
        if not isinstance(report, dict):
            continue
        fit = (cell.estimator, cell.system, cell.seed, json.dumps(report, sort_keys=True))
        if fit not in seen:
            seen.add(fit)
            yield cell, report


def divergence(training: dict) -> str:
    """Why a training (its record in a fit report) diverged, read from its validation curve,
    or ``""`` if it did not (protocol 6.5): under the plateau rule, the validation error
    that was not finite and its step; before it, a curve that ended above
    :data:`~kkl_bench.support.convergence.DIVERGED_RATIO` times its best."""
    curve = training["validation_curve"]
    if "stopped" in training:
        if training["stopped"] != DIVERGED:
            return ""
        step, error = next(((s, e) for s, e in curve if not math.isfinite(e)), curve[-1])
        return f"validation error {error} at step {step:.0f}"
    if outcome(curve) != DIVERGED:
        return ""
    errors = [error for _, error in curve]
    if not all(math.isfinite(error) for error in errors):
        step = next(s for s, e in curve if not math.isfinite(e))
        return f"validation error not finite at step {step:.0f}"
    best, (step, last) = min(errors), curve[-1]
    return (
        f"validation error {last:.3g} at its last step {step:.0f}, {last / best:.3g} times its best"
    )


def diverged_sentence(records: pd.DataFrame, counted: str = "trainings") -> str:
    """The trainings among ``records`` (:func:`training_records`) that diverged, each with
    its reason and, under the plateau rule, the step of the state kept, as one sentence
    (``counted`` names what ``records`` are); ``""`` if none did."""

    def why(row) -> str:
        kept = f" (the state of step {row.best_step:.0f} kept)" if row.stopped == DIVERGED else ""
        return row.diverged + kept

    return _named("Diverged", records[records["diverged"] != ""], records, counted, why)


def capped_sentence(records: pd.DataFrame, counted: str = "trainings") -> str:
    """The trainings among ``records`` (:func:`training_records`) that the plateau rule
    let run to their cap of steps (Converged ``no``: the exceptions protocol 6.5 has the
    board name), each with its steps, how far its learning rate had come down and the
    step of the state kept, as one sentence (``counted`` names what ``records`` are);
    ``""`` if none reached it."""

    def how_far(row) -> str:
        if not row.halvings > 0:
            halved = "its learning rate never halved"
        else:
            times = "once" if row.halvings == 1 else f"{row.halvings:.0f} times"
            halved = f"its learning rate halved {times} (the last at step {row.last_halving:.0f})"
        return f"{row.steps:.0f} steps, {halved}, the state of step {row.best_step:.0f} kept"

    return _named(
        "Reached the cap", records[records["stopped"] == "cap"], records, counted, how_far
    )


def _named(title: str, named: pd.DataFrame, records: pd.DataFrame, counted: str, describe) -> str:
    """``title (k of n counted): `row` on system, seed s, `training`: describe(row); ... .``
    for the ``named`` rows of ``records`` (:func:`training_records`); ``""`` if none."""
    if named.empty:
        return ""
    listed = [
        f"`{row.estimator}` on {row.system}, seed {row.seed}, `{row.training}`: {describe(row)}"
        for row in named.itertuples(index=False)
    ]
    return f"{title} ({len(listed)} of {len(records)} {counted}): " + "; ".join(listed) + "."


def own_records(records: pd.DataFrame, shared: pd.DataFrame) -> pd.DataFrame:
    """The rows of ``records`` that ``shared`` lacks: a track's own trainings, without those
    of the fits it shares with another track (the paper track's, scored again)."""
    merged = records.merge(shared, how="left", indicator=True)
    return records[(merged["_merge"] == "left_only").to_numpy()]


def training_table(records: pd.DataFrame) -> pd.DataFrame:
    """Per row, system and training (in the order met): how many fits ran it, the median
    and range of their steps, how many stopped for each reason (:data:`STOPS`, those that
    occurred), and the median step of the state kept (``Int64`` counts, a median between
    two fits' rounded to the nearest step)."""
    stops = [stop for stop in STOPS if (records["stopped"] == stop).any()]
    rows = []
    for (estimator, system, training), group in records.groupby(
        ["estimator", "system", "training"], sort=False
    ):
        steps = group["steps"]
        rows.append(
            {
                "Row": estimator,
                "System": system,
                "Training": training,
                "Fits": len(group),
                "Steps (median)": steps.median(),
                "Steps (range)": f"{steps.min():,.0f}-{steps.max():,.0f}",
                **{f"Stopped: {stop}": int((group["stopped"] == stop).sum()) for stop in stops},
                "Kept step (median)": group["best_step"].median(),
            }
        )
    table = pd.DataFrame(rows)
    medians = ["Steps (median)", "Kept step (median)"]
    table[medians] = table[medians].round().astype("Int64")  # missing: no step recorded
    return table


def cell_verdicts(cells: pd.DataFrame) -> pd.DataFrame:
    """The board's Converged column for ``cells`` (one track's rows of
    :func:`~kkl_bench.run.results.load_results`): per row, system and task, the verdict
    (:func:`~kkl_bench.support.convergence.verdict`) on the trainings of its seeds' fits,
    as columns ``estimator``, ``system``, ``task``, ``converged``; the cells of rows that
    train nothing (the filters, an unsupported task) are left out."""
    verdicts = (
        cells.groupby(["estimator", "system", "task"], sort=False)["fit_report"]
        .agg(lambda reports: verdict(list(reports)))
        .rename("converged")
        .reset_index()
    )
    return verdicts[verdicts["converged"] != UNTRAINED].reset_index(drop=True)


def _counted(counts: pd.Series, labels: tuple[str, ...]) -> str:
    """``"N label"`` for each of ``labels`` that ``counts`` (verdicts' value counts) holds,
    in that order, joined by commas."""
    return ", ".join(f"{counts[label]} {label}" for label in labels if label in counts)


def converged_sentence(verdicts: pd.DataFrame) -> str:
    """How many of the learned cells in ``verdicts`` (:func:`cell_verdicts`) read each
    verdict, with the share that converged, and where the others are (row and system, with
    their number of cells), as one sentence."""
    counts = verdicts["converged"].value_counts()
    said = _counted(counts, (YES, NO, DIVERGED, UNRECORDED))
    share = counts.get(YES, 0) / len(verdicts)
    others = [
        f"`{estimator}` on {system}, {label}: {len(group)}"
        for (estimator, system, label), group in verdicts[verdicts["converged"] != YES].groupby(
            ["estimator", "system", "converged"], sort=False
        )
    ]
    where = f" ({'; '.join(others)})" if others else ""
    return (
        f"Converged, as the board reads it (per row, system and task, over its seeds' fits): "
        f"{said} of {len(verdicts)} learned cells, {share:.1%} yes{where}."
    )


def converged_by_track(cells: pd.DataFrame) -> str:
    """How many learned cells of each track read Converged ``yes`` (:func:`cell_verdicts`),
    with the other verdicts counted, as one sentence (``cells``: every track's, with a
    ``track`` column); empty if no track has a learned cell."""
    parts = []
    for track, of_track in cells.groupby("track", sort=True):
        counts = cell_verdicts(of_track)["converged"].value_counts()
        if counts.empty:
            continue
        others = _counted(counts, (NO, DIVERGED, UNRECORDED))
        parts.append(
            f"`{track}` {counts.get(YES, 0)} of {counts.sum()} "
            f"({counts.get(YES, 0) / counts.sum():.1%}{'; ' + others if others else ''})"
        )
    if not parts:
        return ""
    return (
        "Learned cells whose Converged reads `yes` (per row, system and task, over its "
        f"seeds' fits), by track: {'; '.join(parts)}."
    )


def rmse_change(before: pd.DataFrame, after: pd.DataFrame, by_regime: bool = False) -> pd.DataFrame:
    """Per row and system (and regime, ``by_regime``), the mean RMSE over the cells (task
    and seed) that both ``before`` and ``after`` scored (status ``ok``), in each, and their
    ratio (after / before); a row or system one of them did not score is left out. A cell
    whose mean RMSE is not finite in either (a diverged trajectory makes it ``inf``) is
    left out of both means, so that they stay paired, and counted in ``Diverged``; where
    every cell is, there is no mean and no ratio."""
    key = ["estimator", "task", "seed"]
    before, after = (cells[cells["status"] == "ok"] for cells in (before, after))
    both = before[[*key, "system", "regime", "rmse_mean"]].merge(
        after[[*key, "rmse_mean"]], on=key, suffixes=(" before", " after")
    )
    finite = np.isfinite(both["rmse_mean before"]) & np.isfinite(both["rmse_mean after"])
    both = both.assign(
        diverged=~finite,
        paired_before=both["rmse_mean before"].where(finite),
        paired_after=both["rmse_mean after"].where(finite),
    )
    groups = ["estimator", "system", "regime"] if by_regime else ["estimator", "system"]
    table = (
        both.groupby(groups, sort=False)
        .agg(
            cells=("task", "size"),
            diverged=("diverged", "sum"),
            before=("paired_before", "mean"),
            after=("paired_after", "mean"),
        )
        .reset_index()
    )
    if by_regime:  # each row and system's regimes in the paper's order, the others after
        order = in_paper_order(table["regime"], REGIME_TITLES)
        table = table.assign(
            group=table.groupby(["estimator", "system"], sort=False).ngroup(),
            rank=table["regime"].map(order.index),
        )
        table = table.sort_values(["group", "rank"], kind="stable").drop(columns=["group", "rank"])
    table["after / before"] = table["after"] / table["before"]
    return table.rename(
        columns={
            "estimator": "Row",
            "system": "System",
            "regime": "Regime",
            "cells": "Cells",
            "diverged": "Diverged",
            "before": "RMSE before",
            "after": "RMSE after",
        }
    )


PROCESSOR, WALL = "processor", "wall"
"""The clocks a fit's seconds are read on (:func:`~kkl_bench.run.results.recorded_seconds`):
its processor time where every phase recorded it, else wall time, which counts whatever
else shared the machine."""


FIT_COST_TEXT = (
    "What each row's fits spent, before and after (read from their fit reports' `spent`, "
    "each fit once; a KKL row's fit includes the Phase 1 it trained or loaded): the median "
    "fit's optimizer steps and seconds, and the training samples per second over all its "
    "fits. Seconds are processor time where every phase of a fit recorded it, else wall "
    "time, which counts whatever else ran on the machine (`Clock`)."
)


def fit_costs(cells: pd.DataFrame) -> pd.DataFrame:
    """One row per distinct fit behind ``cells`` that recorded what it spent
    (``fit_report.spent``): ``estimator``, ``system``, ``seed``, and over its phases
    ``steps`` (optimizer steps), ``samples`` (training samples seen), ``seconds`` and the
    ``clock`` they were read on (:data:`PROCESSOR` or :data:`WALL`). A phase that ran no
    step (a row without a second phase) is left out."""
    records = []
    for cell, report in distinct_fits(cells):
        phases = [
            phase
            for phase in (report.get("spent") or {}).values()
            if isinstance(phase, dict) and phase.get("steps", 0) > 0
        ]
        if not phases:
            continue
        on_processor = all(records_processor_time(phase) for phase in phases)
        records.append(
            {
                "estimator": cell.estimator,
                "system": cell.system,
                "seed": cell.seed,
                "steps": sum(phase.get("steps", 0) for phase in phases),
                "samples": sum(phase.get("samples", 0) for phase in phases),
                "seconds": sum(recorded_seconds(phase) for phase in phases),
                "clock": PROCESSOR if on_processor else WALL,
            }
        )
    columns = ["estimator", "system", "seed", "steps", "samples", "seconds", "clock"]
    return pd.DataFrame(records, columns=columns)


def fit_cost_change(before: pd.DataFrame, after: pd.DataFrame) -> pd.DataFrame:
    """Per row and system that both ``before`` and ``after`` (cells of two results
    folders, a refit's before and after) hold fits of (:func:`fit_costs`): how many fits
    each has, the median fit's steps and seconds, the samples per second over all its
    fits (their samples over their seconds: the training's throughput), and the clock of
    each side's seconds (``processor, wall`` where its fits differ)."""

    def per_row(cells: pd.DataFrame) -> pd.DataFrame:
        return (
            fit_costs(cells)
            .groupby(["estimator", "system"], sort=False)
            .agg(
                fits=("seed", "size"),
                steps=("steps", lambda steps: round(steps.median())),
                seconds=("seconds", "median"),
                samples=("samples", "sum"),
                total_seconds=("seconds", "sum"),
                clock=("clock", lambda clocks: ", ".join(sorted(set(clocks)))),
            )
            .assign(throughput=lambda rows: rows["samples"] / rows["total_seconds"])
            .drop(columns=["samples", "total_seconds"])
        )

    both = per_row(before).merge(
        per_row(after), left_index=True, right_index=True, suffixes=(" before", " after")
    )
    order = [
        f"{column} {side}"
        for column in ("fits", "steps", "seconds", "throughput", "clock")
        for side in ("before", "after")
    ]
    headers = {
        "fits": "Fits",
        "steps": "Steps (median)",
        "seconds": "Seconds (median)",
        "throughput": "Samples/s",
        "clock": "Clock",
    }
    return (
        both[order]
        .reset_index()
        .rename(
            columns={
                "estimator": "Row",
                "system": "System",
                **{
                    f"{column} {side}": f"{header} {side}"
                    for column, header in headers.items()
                    for side in ("before", "after")
                },
            }
        )
    )
