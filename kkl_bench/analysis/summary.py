"""One row per (estimator, system, regime) from stored cells, and the numbers derived from it.

:func:`summary_table` aggregates a track's cells over training seeds: for each
seed the mean over the test trajectories, then the mean of those over the
seeds and their standard deviation, with the significance marks of
:mod:`kkl_bench.analysis.significance`; :func:`track_summary` compares every other
track with the paper track. Nothing here recomputes a metric: it reads what
the harness recorded. Tables of these numbers are in :mod:`kkl_bench.analysis.leaderboard`.
"""

from __future__ import annotations

import importlib.resources
import io
import math

import numpy as np
import pandas as pd

from kkl_bench import families, variants
from kkl_bench.analysis.significance import MARGIN, mark_column
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.run.results import mean_and_std, mean_fit_seconds
from kkl_bench.suite.tracks import find_track
from kkl_bench.support import convergence

PAPER_PREFIX = "paper:"
SYSTEM_TITLES = {
    "duffing": "Duffing",
    "vdp": "Van der Pol",
    "rossler": "Rossler",
    "lorenz": "Lorenz",
    "fitzhugh_nagumo": "FitzHugh-Nagumo",
    "chua": "Chua",
    **{f"lorenz96-n{n}": f"Lorenz-96 n={n}" for n in (5, 10, 20, 40, 80, 160)},
}
"""Table and figure titles of the built-in systems, in the order tables show them."""
REGIME_TITLES = {"zero": "Zero", "constant": "Const", "sinusoid": "Sin", "square": "Sqr"}


def paper_results() -> pd.DataFrame:
    """The HyperKKL paper's Tables 1-2: columns method, system, regime, rmse, smape_percent."""
    text = importlib.resources.files("kkl_bench").joinpath("paper_results.csv").read_text()
    return pd.read_csv(io.StringIO(text))


def _seed_mean_and_std(per_seed: list[float]) -> tuple[float, float]:
    """Mean over seeds and the standard deviation over seeds (ddof 1; NaN for one seed)."""
    if not per_seed:
        return math.nan, math.nan
    if not all(math.isfinite(value) for value in per_seed):
        return math.inf, math.inf
    values = np.asarray(per_seed)
    return float(values.mean()), float(values.std(ddof=1)) if len(values) > 1 else math.nan


def _spent(cells: pd.DataFrame) -> dict[str, float]:
    """Phase-1 and second-phase steps and samples from the first cell's fit report."""
    reports = cells["fit_report"] if "fit_report" in cells else pd.Series([{}] * len(cells))
    spent = next((r["spent"] for r in reports if isinstance(r, dict) and "spent" in r), {})
    return {
        f"{phase}_{unit}": spent.get(phase, {}).get(unit, math.nan)
        for phase in ("phase1", "phase2")
        for unit in ("steps", "samples")
    }


def versions(results: pd.DataFrame) -> pd.DataFrame:
    """Per cell: its ``protocol`` and ``toolkit`` (KKL toolkit version; None where the
    estimator records none)."""
    reports = results["fit_report"] if "fit_report" in results else pd.Series([{}] * len(results))
    return pd.DataFrame(
        {
            "protocol": results["protocol"].to_numpy(),
            "toolkit": pd.array(
                [r.get("toolkit") if isinstance(r, dict) else None for r in reports], dtype="Int64"
            ),
        },
        index=results.index,
    )


def version_groups(results: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """``results`` split by the versions that must not mix: ``{label: cells}``.

    One group (labelled ``""``) when every cell agrees; cells that record no
    toolkit version join whichever group they are in by protocol.
    """
    found = versions(results)
    toolkits = sorted(found["toolkit"].dropna().unique())
    if found["protocol"].nunique() <= 1 and len(toolkits) <= 1:
        return {"": results}
    groups = {}
    for protocol in sorted(set(found["protocol"])):
        for toolkit in toolkits or [None]:
            mask = (found["protocol"] == protocol) & (
                found["toolkit"].isna() | (found["toolkit"] == toolkit)
            )
            if mask.any():
                groups[f"protocol {protocol}, KKL toolkit {toolkit}"] = results[mask]
    return groups


def check_not_mixed(results: pd.DataFrame) -> None:
    """Raise ``ValueError`` naming what differs if the cells mix protocol or toolkit versions."""
    groups = version_groups(results)
    if len(groups) > 1:
        counts = "; ".join(f"{label}: {len(cells)} cells" for label, cells in groups.items())
        raise ValueError(
            f"the results mix versions that one table must not mix ({counts}); rerun the old "
            "cells, keep them in another results directory, or pass --by-version to tabulate "
            "each group separately"
        )


def summary_table(
    results: pd.DataFrame, with_paper: bool = False, margin: float = MARGIN
) -> pd.DataFrame:
    """One row per (estimator, system, regime): the numbers every table shows.

    Columns: estimator, family (:mod:`kkl_bench.families`), system, regime, status, n_seeds, n_test (per seed),
    n_diverged (over all seeds), rmse_mean and rmse_seed_std (mean and
    standard deviation over seeds of the per-seed mean RMSE), smape_mean,
    smape_seed_std, nrmse_mean, fit_time_s, estimate_us_per_step (means over
    seeds), rmse_median (over all trajectories of all seeds), settling_median_s
    and n_unsettled (median settling time over all trajectories and how many
    never settled; NaN and 0 for cells recorded without settling times), task,
    track, protocol, map quality, the steps and samples spent
    (``phase1_steps`` ...), ``converged`` (whether the trainings converged:
    :func:`kkl_bench.support.convergence.verdict` over the seeds' fits), ``mark`` (``best``, ``tied`` or empty, see
    :mod:`kkl_bench.analysis.significance`; ``margin`` is its practical-equivalence margin) and ``rmse_trajectories`` (per seed, per
    trajectory; ``(n_seeds, n_test)`` nested lists, not written to CSV).
    """
    if "seed" not in results:
        results = results.assign(seed=0)
    columns = ["estimator", "system", "regime"]
    rows = []
    for (estimator, system, regime), cells in results.groupby(columns, sort=False):
        cells = cells.sort_values("seed")
        scored = cells[cells["status"] == "ok"]
        rmse_by_seed = [list(values) for values in scored["rmse"]]
        rmse_mean, rmse_std = _seed_mean_and_std([mean_and_std(v)[0] for v in rmse_by_seed])
        smape_mean, smape_std = _seed_mean_and_std([mean_and_std(v)[0] for v in scored["smape"]])
        pooled = [value for values in rmse_by_seed for value in values]
        settling = [value for values in scored.get("settling_time_s", []) for value in values]
        rows.append(
            {
                "estimator": estimator,
                "family": families.row_family(estimator, _recorded_family(cells)),
                "system": system,
                "regime": regime,
                "status": _status(cells, scored),
                "n_seeds": len(scored),
                "n_test": len(rmse_by_seed[0]) if rmse_by_seed else 0,
                "n_diverged": sum(not math.isfinite(v) for values in rmse_by_seed for v in values),
                "rmse_mean": rmse_mean,
                "rmse_seed_std": rmse_std,
                "smape_mean": smape_mean,
                "smape_seed_std": smape_std,
                "nrmse_mean": _seed_mean_and_std([mean_and_std(v)[0] for v in scored["nrmse"]])[0],
                "fit_time_s": mean_fit_seconds(scored),
                "estimate_us_per_step": scored["estimate_us_per_step"].mean(),
                "rmse_median": float(np.median(pooled)) if pooled else math.nan,
                "settling_median_s": float(np.median(settling)) if settling else math.nan,
                "n_unsettled": sum(not math.isfinite(value) for value in settling),
                "task": cells["task"].iloc[0],
                "track": cells["track"].iloc[0] if "track" in cells else PAPER_TRACK,
                "protocol": cells["protocol"].iloc[0],
                **_map_quality(cells),
                **_spent(cells),
                "converged": convergence.verdict(cells.get("fit_report", [])),
                "rmse_trajectories": rmse_by_seed,
            }
        )
    summary = pd.DataFrame(rows)
    summary["mark"] = _marks(summary, margin)
    return with_paper_rows(summary) if with_paper else summary


def with_paper_rows(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` (the paper track's :func:`summary_table`) followed by the paper's own
    numbers, one row per method and cell, named ``PAPER_PREFIX + method`` and never marked."""
    paper = paper_results().rename(columns={"rmse": "rmse_mean", "smape_percent": "smape_mean"})
    paper["estimator"] = PAPER_PREFIX + paper.pop("method")
    paper["status"] = "ok"
    paper["n_diverged"] = 0
    paper["mark"] = ""
    return pd.concat([summary, paper], ignore_index=True)


def _recorded_family(cells: pd.DataFrame) -> str:
    """The family the newest of a row's cells recorded (empty if none did)."""
    recorded = [family for family in cells.get("family", []) if isinstance(family, str) and family]
    return recorded[-1] if recorded else ""


def _status(cells: pd.DataFrame, scored: pd.DataFrame) -> str:
    """A row's status in a cell: ``ok`` when every seed scored, ``unsupported`` when the
    estimator cannot handle the task, else ``error``."""
    if len(scored) and len(scored) == len(cells):
        return "ok"
    if (cells["status"] == "unsupported").all():
        return "unsupported"
    return "error"


def unsupported_reasons(summary_cells: pd.DataFrame) -> list[tuple[str, list[str], str]]:
    """``(row, systems, reason)`` for every distinct reason a row's unsupported cells give
    (``summary_cells``: the cells of one track as :func:`~kkl_bench.run.results.load_results`
    reads them), ``systems`` those where it is given, in the paper's order; rows in order."""
    unsupported = summary_cells[summary_cells["status"] == "unsupported"]
    reasons = [
        (row, in_paper_order(cells["system"], SYSTEM_TITLES), reason)
        for (row, reason), cells in unsupported.groupby(["estimator", "error"])
    ]
    order = {system: position for position, system in enumerate(SYSTEM_TITLES)}
    return sorted(reasons, key=lambda entry: (entry[0], order.get(entry[1][0], len(order))))


def _marks(summary: pd.DataFrame, margin: float) -> pd.Series:
    """The significance mark of every row, decided column by column."""
    marks = pd.Series("", index=summary.index, dtype=object)
    for _, column in summary.groupby(["system", "regime"], sort=False):
        scored = column[(column["status"] == "ok") & (column["n_seeds"] > 0)]
        if scored.empty or len({len(t[0]) for t in scored["rmse_trajectories"]}) != 1:
            continue  # no entries, or different test sets: nothing to compare
        decided = mark_column(
            {index: np.asarray(values) for index, values in scored["rmse_trajectories"].items()},
            margin,
        )
        for index, mark in decided.items():
            marks[index] = mark
    return marks


MAP_QUALITY = ("reconstruction_rmse_unforced", "reconstruction_rmse_forced", "pde_residual_forced")
"""Map-quality numbers a KKL estimator reports (see :func:`kkl_bench.kkl.autonomous.map_quality`)."""


def _map_quality(cells: pd.DataFrame) -> dict[str, float]:
    """The map-quality numbers in the cells' fit reports (NaN where none are reported)."""
    reports = cells["fit_report"] if "fit_report" in cells else pd.Series([{}] * len(cells))
    quality = next(
        (r["map_quality"] for r in reports if isinstance(r, dict) and "map_quality" in r), {}
    )
    return {key: quality.get(key, math.nan) for key in MAP_QUALITY}


def in_paper_order(names: pd.Series, known: dict[str, str]) -> list[str]:
    """Distinct ``names``: the paper's ones in its order, then any others sorted."""
    present = set(names)
    return [name for name in known if name in present] + sorted(present - set(known))


def task_order(summary: pd.DataFrame) -> list[str]:
    """The regimes (tasks) of ``summary``, one track's, in its track file's order (the
    paper's order for the paper track; sorted if the track is not installed here)."""
    present = set(summary["regime"])
    track = find_track(summary["track"].iloc[0] if "track" in summary else PAPER_TRACK)
    declared = track.task_names() if track else list(REGIME_TITLES)
    return [name for name in declared if name in present] + sorted(present - set(declared))


def _finite_mean(rmse_trajectories: list[list[float]]) -> float:
    """Mean RMSE over the trajectories (of all seeds) that did not diverge."""
    values = [v for seed in rmse_trajectories for v in seed if math.isfinite(v)]
    return float(np.mean(values)) if values else math.nan


def _reference(track: str, regime: str) -> str:
    """The paper task ``track``'s task ``regime`` is compared with (its own name if the
    track is not installed here)."""
    declared = find_track(track)
    if declared is None or regime not in declared.task_names():
        return regime
    return declared.task(regime).reference


def condition(track: str, regime: str) -> str:
    """What task ``regime`` of ``track`` changes beside its reference regime: its name
    without the reference (``params10-square`` -> ``params10``, ``square-sigma0.1`` ->
    ``sigma0.1``), or the whole name if it does not contain it (``chirp``)."""
    reference = _reference(track, regime)
    if regime.startswith(f"{reference}-"):
        return regime[len(reference) + 1 :]
    if regime.endswith(f"-{reference}"):
        return regime[: -len(reference) - 1]
    return regime


def track_summary(results: pd.DataFrame, by_condition: bool = False) -> pd.DataFrame:
    """Per estimator and track: RMSE relative to the estimator's own paper-track RMSE.

    For each of the track's cells, the mean RMSE over its non-diverged
    trajectories (all seeds) divided by the same estimator's mean paper-track
    RMSE on the same system under the task's reference regime (declared in
    the track file); ``ratio`` is the geometric mean of these over the
    track's cells and ``median`` their median (one system can dominate the
    mean). ``n_diverged`` and ``n_trajectories`` count the track's
    diverged and scored trajectories. A track with no cell to compare (one of
    other systems, such as ``more-systems``) is left out. Columns: estimator,
    track, ratio, median, n_cells, n_diverged, n_trajectories; ``by_condition``: one row
    per estimator, track and :func:`condition` (column ``condition``, after
    ``track``), e.g. the mismatch track's ``params10``, ``params25`` and ``sensor``.
    """
    if "track" not in results:
        results = results.assign(track=PAPER_TRACK)
    per_track = {
        track: summary_table(cells) for track, cells in results.groupby("track", sort=False)
    }
    return relative_summary(per_track, by_condition)


def relative_summary(
    per_track: dict[str, pd.DataFrame], by_condition: bool = False
) -> pd.DataFrame:
    """:func:`track_summary` from each track's :func:`summary_table` (track name -> table,
    the paper track's among them), for a caller that has them already."""
    if PAPER_TRACK not in per_track:
        raise ValueError("the results hold no paper-track cells to compare the tracks with")
    paper = per_track[PAPER_TRACK].set_index(["estimator", "system", "regime"])
    cells = []
    for track, summary in per_track.items():
        if track == PAPER_TRACK:
            continue
        for cell in summary[summary["status"] == "ok"].itertuples():
            # a +logged row is compared with its estimator's own paper-track fit
            nominal = variants.split_logged(cell.estimator)[0]
            key = (nominal, cell.system, _reference(track, cell.regime))
            ratio = math.nan
            if key in paper.index and paper.loc[key, "status"] == "ok":
                ratio = _finite_mean(cell.rmse_trajectories) / _finite_mean(
                    paper.loc[key, "rmse_trajectories"]
                )
            cells.append(
                {
                    "estimator": cell.estimator,
                    "track": track,
                    "condition": condition(track, cell.regime),
                    "ratio": ratio if math.isfinite(ratio) and ratio > 0 else math.nan,
                    "n_diverged": cell.n_diverged,
                    "n_trajectories": cell.n_test * cell.n_seeds,
                }
            )
    keys = ["estimator", "track", *(["condition"] if by_condition else [])]
    columns = [*keys, "ratio", "median", "n_cells", "n_diverged", "n_trajectories"]
    if not cells:
        return pd.DataFrame(columns=columns)
    frame = (
        pd.DataFrame(cells)
        .groupby(keys, sort=False)
        .agg(
            ratio=("ratio", lambda r: float(np.exp(np.log(r.dropna()).mean()))),
            median=("ratio", lambda r: float(r.median())),
            n_cells=("ratio", "count"),
            n_diverged=("n_diverged", "sum"),
            n_trajectories=("n_trajectories", "sum"),
        )
        .reset_index()[columns]
    )
    comparable = frame.groupby("track")["n_cells"].transform("sum") > 0
    return frame[comparable].reset_index(drop=True)
