"""The scaling study: how each estimator's cost and error grow with the state dimension.

On Lorenz-96 with ``n = 5, 10, ..., 160`` states (:data:`SIZES`; the ``more-systems`` track),
per estimator:

* the RMSE, from the track's cells in the results store (means over the four
  regimes and the training seeds), and the fit time: the time of every
  training the fit used, wherever it ran (:func:`~kkl_bench.run.results.fit_seconds`; a KKL
  observer's shared Phase 1 counts in each KKL row);
* the online cost, microseconds per trajectory-step of ``estimate`` at a batch
  of 20 trajectories and of 1, measured here side by side in one run: every
  fitted estimator of every size is loaded first (from the cache the run
  filled), then each is timed ``repeats`` times in turn, round-robin, on one
  thread, keeping the fastest of its repeats. A later timing run may add the
  rows an earlier one lacks (a new estimator, a size trained since), timing the
  reference EKF at the same sizes beside them: every row carries the EKF's cost
  *of its own run*, and every comparison with the EKF uses it;
* the exponent ``p`` of the RMSE and of each cost curve, ``value ~ n^p``, the least-squares
  slope of ``log cost`` against ``log n``.

Everything the study reports is in the frame :func:`scaling_frame` returns;
:func:`render_scaling` and :func:`scaling_figure` present it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from kkl_bench import families
from kkl_bench.analysis.summary import summary_table
from kkl_bench.run.results import mean_fit_seconds
from kkl_bench.support import convergence
from kkl_bench.systems.lorenz96 import SIZES

TRACK = "more-systems"
REGIME = "sinusoid"
"""The task whose test trajectories the online cost is timed on."""
BATCHES = (20, 1)
STEPS = 200
"""Samples per timed call: the cost per trajectory-step does not depend on the horizon, and
the filters' Python loops at n = 40 would take minutes over the whole one."""
REFERENCE = "ekf"
"""The estimator every timing run also times, at each size it times anything."""
LOCAL_FILTER = "enkf[localization=3]"
"""The localized ensemble filter (protocol 6.4), built for large rings: the study also says
where each row is cheaper online than it."""
ONLINE = tuple(f"us_per_step_batch{batch}" for batch in BATCHES)
REFERENCE_ONLINE = tuple(f"{REFERENCE}_{column}" for column in ONLINE)
"""The reference's online costs in a row's own timing run, beside the row's :data:`ONLINE`."""
ENGINE_ONLINE = tuple(f"reference_engine_{column}" for column in ONLINE)
"""A row timed on its compiled engine: its reference engine's online costs in the same run."""
TIMING_COLUMNS = (
    "timing_run",
    "timing_commit",
    "engine",
    "models",
    *ONLINE,
    *REFERENCE_ONLINE,
    *ENGINE_ONLINE,
)
"""What a study stores of its timings, per (estimator, n): the timing run that measured the
row (1, 2, ...), the code's git commit in that run, the engine timed (as ``kkl-bench cost``
names it: ``compiled`` or ``reference`` for a filter with engines, ``numpy`` for one without,
``torch`` for a network), the models timed (:data:`MODELS`), its online costs, the
reference's costs in that run and, beside a compiled row, its reference engine's."""
MODELS = ("trained", "untrained")
"""What a timing run timed: the trained models of the cache (:func:`fit_from_cache`), or
models of the same structure with their trainings cut short (:func:`fit_untrained`)."""
GROWTHS = {
    "rmse": "RMSE (mean over regimes)",
    "fit_time_s": "fit time (s)",
    "us_per_step_batch20": "µs / trajectory-step, batch 20",
    "us_per_step_batch1": "µs / trajectory-step, batch 1",
}
"""Everything whose growth with n gets an exponent and a panel: the error and the costs."""
RMSE_RATIO = "rmse_over_reference"
"""A row's RMSE over the reference's at the same n."""
SPEEDUPS = tuple(f"speedup_batch{batch}" for batch in BATCHES)
"""The reference's online cost in a row's own timing run over the row's, per batch: how many
times cheaper online than the reference the row is (above 1: cheaper)."""


def system_name(n: int) -> str:
    return f"lorenz96-n{n}"


def cell_summary(results: pd.DataFrame, sizes: Sequence[int] = SIZES) -> pd.DataFrame:
    """Per (estimator, n): status, RMSE and fit time, means over the track's regimes.

    ``results``: the store's cells (:func:`~kkl_bench.run.results.load_results`).
    Columns: estimator, n, status (``ok``; ``unsupported`` when every cell not scored
    is, the estimator refusing the system; :data:`NOT_RUN` at a size the results hold
    cells of but none of this estimator, or not of every regime the results hold; else
    ``error``), reason (what the first cell
    not scored says: the unsupported reason, or the error's last line), rmse, nrmse,
    fit_time_s (:func:`~kkl_bench.run.results.mean_fit_seconds`: the trainings' recorded
    times, else the fit's wall time for an estimator that does not train; NaN for a model
    trained before training times were recorded)
    and converged (:func:`kkl_bench.support.convergence.worst` of its cells).
    """
    track, wanted = _lorenz96_cells(results, sizes)
    if track.empty:
        raise ValueError(
            f"the results hold no {TRACK} cells of {', '.join(wanted)}; run "
            f"`kkl-bench run --track {TRACK} --estimator all` first"
        )
    regimes = sorted(set(track["regime"]))  # what the study holds: a run may pick regimes
    rows = []
    for (estimator, system), cells in summary_table(track).groupby(["estimator", "system"]):
        of = track[(track["estimator"] == estimator) & (track["system"] == system)]
        absent = [regime for regime in regimes if regime not in set(of["regime"])]
        if absent:  # a mean over fewer regimes would not be the row's RMSE
            rows.append(_not_run(estimator, wanted[system], f"no result for {', '.join(absent)}"))
            continue
        if (fits := _fits(of)) > 1:  # the regimes' cells were not made by one model
            reason = f"its cells come from {fits} fits (a rerun with --force that was cut off)"
            rows.append(_not_run(estimator, wanted[system], reason, overwrite=True))
            continue
        ok = cells[cells["status"] == "ok"]
        failed = of[of["status"] != "ok"]
        rows.append(
            {
                "estimator": estimator,
                "n": wanted[system],
                "status": _status(failed),
                "reason": None if failed.empty else _last_line(failed["error"].iloc[0]),
                "rmse": ok["rmse_mean"].mean() if failed.empty else math.nan,
                "nrmse": ok["nrmse_mean"].mean() if failed.empty else math.nan,
                "fit_time_s": mean_fit_seconds(of) if failed.empty else math.nan,
                "converged": convergence.worst(cells["converged"]),
                "overwrite": False,
            }
        )
    return _with_sizes_not_run(pd.DataFrame(rows))


NOT_RUN = "not run"
"""The status of a size the results hold cells of, for an estimator that has none there,
lacks some of the regimes the results hold, or has cells of one seed from different fits."""


def _not_run(estimator: str, n: int, reason: str, overwrite: bool = False) -> dict:
    """A :data:`NOT_RUN` row of :func:`cell_summary`; ``overwrite``: the cells that make it
    must replace cells on disk (``kkl-bench run --force``)."""
    return {
        "estimator": estimator,
        "n": n,
        "status": NOT_RUN,
        "reason": reason,
        "converged": "",
        "overwrite": overwrite,
    }


def _fits(cells: pd.DataFrame) -> int:
    """How many fits made ``cells`` (one estimator on one system), the most of any seed.

    Every cell of one fit keeps that fit's report; a model loaded from the cache keeps the
    report it was trained with. Two reports in one seed mean cells of two trainings: a
    ``--force`` rerun cut off after scoring some of the regimes."""
    if "fit_report" not in cells:
        return 1
    reports = cells["fit_report"].map(
        lambda report: json.dumps(report, sort_keys=True, default=str)
    )
    return int(reports.groupby(cells["seed"]).nunique().max())


def _with_sizes_not_run(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` with a :data:`NOT_RUN` row for each (estimator, n) it lacks among the
    sizes it holds: a cell never run is shown as such, not left out of the study."""
    have = set(zip(summary["estimator"], summary["n"], strict=True))
    missing = [
        _not_run(estimator, n, "no result stored")
        for estimator in sorted(set(summary["estimator"]))
        for n in sorted(set(summary["n"]))
        if (estimator, n) not in have
    ]
    return pd.concat([summary, pd.DataFrame(missing)], ignore_index=True) if missing else summary


def curve_frame(results: pd.DataFrame, seed: int = 0, sizes: Sequence[int] = SIZES) -> pd.DataFrame:
    """The validation curves (protocol 6.5) of every fit of seed ``seed`` on the track's
    Lorenz-96 sizes, one row per point: estimator, n, training (where in the fit report
    the curve is), step, error. A fit is read from one of its cells (every regime's
    cell keeps the same report); a model trained at another size and applied at this one
    (its report's ``trained_on``) gives its curve once, at the size it trained at."""
    track, wanted = _lorenz96_cells(results, sizes)
    fits = track[(track["seed"] == seed) & (track["status"] == "ok")]
    fits = fits.drop_duplicates(["estimator", "system"])
    rows = []
    for fit in fits.itertuples():
        report = fit.fit_report if isinstance(fit.fit_report, dict) else {}
        trained_at = wanted.get(report.get("trained_on"), wanted[fit.system])
        rows += [
            (fit.estimator, trained_at, training, step, error)
            for training, curve in convergence.curves(report)
            for step, error in curve
        ]
    frame = pd.DataFrame(rows, columns=["estimator", "n", "training", "step", "error"])
    return frame.drop_duplicates(["estimator", "n", "training", "step"], ignore_index=True)


def _lorenz96_cells(
    results: pd.DataFrame, sizes: Sequence[int]
) -> tuple[pd.DataFrame, dict[str, int]]:
    """The track's cells of Lorenz-96 at ``sizes``, and each size's system name -> n."""
    wanted = {system_name(n): n for n in sizes}
    return results[(results.get("track") == TRACK) & results["system"].isin(wanted)], wanted


def _status(failed: pd.DataFrame) -> str:
    """``ok`` if no cell of an (estimator, n) failed, ``unsupported`` if the estimator
    refused every one that did, else ``error``."""
    if failed.empty:
        return "ok"
    return "unsupported" if (failed["status"] == "unsupported").all() else "error"


def _last_line(error: object) -> str:
    """An error's last non-empty line (a traceback's exception), or a one-line reason."""
    lines = [line for line in str(error).splitlines() if line.strip()]
    return lines[-1] if lines else "error"


def scaling_frame(cells: pd.DataFrame, timings: pd.DataFrame) -> pd.DataFrame:
    """One row per (estimator, n): :func:`cell_summary`'s columns, the row's family
    (:mod:`kkl_bench.families`), the timings
    (:func:`timing_frame`, :func:`add_timings`) and the ratios to the reference
    (:data:`RMSE_RATIO`, :data:`SPEEDUPS`; NaN where either side has no number)."""
    frame = cells.merge(timings, on=["estimator", "n"], how="left")
    frame.insert(1, "family", frame["estimator"].map(families.row_family))
    costs = [*ONLINE, *REFERENCE_ONLINE, *ENGINE_ONLINE]
    frame[costs] = frame[costs].astype(float)  # NaN where untimed, also when nothing is
    return with_ratios(frame).sort_values(["estimator", "n"]).reset_index(drop=True)


def with_ratios(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` (estimator, n, rmse, :data:`ONLINE`, :data:`REFERENCE_ONLINE`) with
    :data:`RMSE_RATIO` and :data:`SPEEDUPS` (NaN where either side has no number)."""
    reference_rmse = frame[frame["estimator"] == REFERENCE].set_index("n")["rmse"]
    ratios = {RMSE_RATIO: frame["rmse"] / frame["n"].map(reference_rmse).astype(float)}
    for speedup, cost, reference in zip(SPEEDUPS, ONLINE, REFERENCE_ONLINE, strict=True):
        ratios[speedup] = frame[reference] / frame[cost]
    return frame.assign(**ratios)


def trained_fit_times(frame: pd.DataFrame) -> pd.Series:
    """``frame``'s fit times, NaN for a row that does not train (its family is not
    ``learned``, :mod:`kkl_bench.families`): a filter's fit time is the noise of building
    its model, not a cost that grows."""
    return frame["fit_time_s"].where(families.of_rows(frame) == "learned")


def exponents(frame: pd.DataFrame) -> pd.DataFrame:
    """Per estimator, the fitted exponent ``p`` of ``value ~ n^p`` for the RMSE and each
    cost (:data:`GROWTHS`; NaN with fewer than two finite, positive points, and for the
    fit time of a row that does not train, see :func:`trained_fit_times`)."""
    frame = frame.assign(fit_time_s=trained_fit_times(frame))
    rows = []
    for estimator, rows_of in frame.groupby("estimator"):
        row = {"estimator": estimator}
        for column in GROWTHS:
            points = rows_of[np.isfinite(rows_of[column]) & (rows_of[column] > 0)]
            row[column] = (
                float(np.polyfit(np.log(points["n"]), np.log(points[column]), 1)[0])
                if len(points) >= 2
                else math.nan
            )
        rows.append(row)
    return pd.DataFrame(rows)


def cost_against(frame: pd.DataFrame, against: str, batch: int) -> pd.Series:
    """Per row of ``frame``, the online cost at ``batch`` of ``against`` at the row's size,
    timed in the row's own timing run; NaN where it was not (costs of two runs are not
    compared). The reference is timed in every run, beside each row
    (:data:`REFERENCE_ONLINE`)."""
    column = ONLINE[BATCHES.index(batch)]
    if against == REFERENCE:
        return frame[REFERENCE_ONLINE[BATCHES.index(batch)]]
    other = frame[frame["estimator"] == against].set_index("n")
    same_run = frame["timing_run"] == frame["n"].map(other["timing_run"])
    return frame["n"].map(other[column]).where(same_run)


def crossover(frame: pd.DataFrame, against: str = REFERENCE) -> dict[tuple[str, int], list[int]]:
    """Per (estimator other than ``against``, batch): the measured sizes ``n`` at which it is
    cheaper online than ``against`` timed in the same run (:func:`cost_against`),
    ascending (empty if it never is)."""
    result = {}
    for batch, column in zip(BATCHES, ONLINE, strict=True):
        theirs = cost_against(frame, against, batch)
        for estimator, rows_of in frame[frame["estimator"] != against].groupby("estimator"):
            cheaper = rows_of[rows_of[column] < theirs[rows_of.index]]
            result[estimator, batch] = sorted(int(n) for n in cheaper["n"])
    return result
