"""Rows against rows: two estimators cell by cell (paired bootstrap), and every row against
the particle filter's Bayes limit."""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence

import numpy as np
import pandas as pd

from kkl_bench import families, variants
from kkl_bench.analysis.document import Table
from kkl_bench.analysis.significance import compare
from kkl_bench.analysis.summary import (
    PAPER_PREFIX,
    REGIME_TITLES,
    SYSTEM_TITLES,
    condition,
    in_paper_order,
    task_order,
)
from kkl_bench.suite.tracks import find_track

COMPARISON_COLUMNS = (
    "cell",
    "system",
    "regime",
    "rmse_a",
    "rmse_b",
    "ratio",
    "low",
    "high",
    "verdict",
)
"""Columns of :func:`comparison_frame`."""


def comparison_frame(summary: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per cell both estimators scored: ``a``'s RMSE over ``b``'s, its 90 % bootstrap
    interval (``low``, ``high``) and the verdict of :func:`kkl_bench.analysis.significance.compare`
    (``"a lower"``, ``"b lower"``, ``"not distinguishable"`` or ``"diverged"``), in paper
    order; columns :data:`COMPARISON_COLUMNS`."""
    indexed = summary.set_index(["estimator", "system", "regime"])
    for name in (a, b):
        if name not in set(summary["estimator"]):
            raise ValueError(
                f"no results for {name!r}; estimators in the results: "
                f"{', '.join(sorted(set(summary['estimator'])))}"
            )
    rows = []
    for system in in_paper_order(summary["system"], SYSTEM_TITLES):
        for regime in in_paper_order(summary["regime"], REGIME_TITLES):
            if (a, system, regime) not in indexed.index or (b, system, regime) not in indexed.index:
                continue
            first, second = indexed.loc[(a, system, regime)], indexed.loc[(b, system, regime)]
            if first["status"] != "ok" or second["status"] != "ok":
                continue
            result = compare(
                np.asarray(first["rmse_trajectories"]), np.asarray(second["rmse_trajectories"])
            )
            rows.append(
                {
                    "cell": f"{SYSTEM_TITLES.get(system, system)} {REGIME_TITLES.get(regime, regime)}",
                    "system": system,
                    "regime": regime,
                    "rmse_a": first["rmse_mean"],
                    "rmse_b": second["rmse_mean"],
                    **result,
                }
            )
    return pd.DataFrame(rows, columns=list(COMPARISON_COLUMNS))


def comparison_cells(
    frame: pd.DataFrame, last: Sequence[str], headers: Sequence[str], id: str = ""
) -> Table:
    """The rows of a :func:`comparison_frame` as shown: cell, both RMSEs, ratio and
    ``[low, high]`` (3 significant digits; ``a trajectory diverged`` where the bootstrap
    has no interval), then the row's item of ``last``, under ``headers`` (six)."""
    keys = ["cell", "rmse_a", "rmse_b", "ratio", "interval", "last"]
    rows = [
        [
            row.cell,
            f"{row.rmse_a:.3g}",
            f"{row.rmse_b:.3g}",
            f"{row.ratio:.3g}",
            f"[{row.low:.3g}, {row.high:.3g}]"
            if row.verdict != "diverged"
            else "a trajectory diverged",
            extra,
        ]
        for row, extra in zip(frame.itertuples(), last, strict=True)
    ]
    return Table(pd.DataFrame(rows, columns=keys), dict(zip(keys, headers, strict=True)), id=id)


def comparison_table(summary: pd.DataFrame, a: str, b: str) -> Table:
    """:func:`comparison_frame` with verdicts naming the estimators."""
    frame = comparison_frame(summary, a, b)
    names = {"a lower": f"{a} lower", "b lower": f"{b} lower"}
    verdicts = [names.get(verdict, verdict) for verdict in frame["verdict"]]
    headers = ["Cell", f"RMSE {a}", f"RMSE {b}", "ratio", "90 % interval", "verdict (5 %)"]
    return comparison_cells(frame, verdicts, headers, id="comparison")


LIMIT = "particle_filter"
"""The row the other estimators are measured against in :func:`limit_frame`."""
TRUTH_LIMIT = variants.truth_row(LIMIT)
"""The limit where the tasks' truth is not what the estimators were fitted with (``noise``,
``far-init``): the particle filter told each task's noise and initial box."""


def particle_count(row: str) -> int | None:
    """The particle count of a particle-filter row that differs from :data:`LIMIT` in its
    count alone (``particle_filter``, ``particle_filter[n=20000]``); None for every other
    row (another proposal, a ``+truth`` or ``+logged`` row, another estimator)."""
    name, suffix = variants.split_row(row)
    if suffix or variants.base_name(name) != LIMIT:
        return None
    estimator = variants.build(name)
    default = type(estimator)()
    if {**estimator.get_params(), "n": default.n} != default.get_params():
        return None
    return estimator.n


def _nominal_plant(summary: pd.DataFrame) -> pd.Series:
    """Per row of ``summary``: whether its task's data come from the nominal model (True
    where the track or task is not known here)."""

    def nominal(track: str, regime: str) -> bool:
        definition = find_track(track)
        if definition is None or regime not in definition.task_names():
            return True
        return definition.task(regime).plant.nominal

    tracks = summary["track"] if "track" in summary else pd.Series("paper", summary.index)
    return pd.Series(
        [nominal(t, r) for t, r in zip(tracks, summary["regime"], strict=True)], summary.index
    )


def limit_rows(summary: pd.DataFrame) -> pd.DataFrame:
    """Per cell (index ``system, regime``) of ``summary`` where a limit was scored: the row
    that stands for the Bayes limit (``row``) and its mean RMSE (``rmse``). The
    ``+truth`` row where there is one (the tasks' truth differs from what the estimators
    were fitted with); else the particle filter with the most particles scored in the
    cell, at least :data:`LIMIT`'s (protocol section 6.1: a cell where doubling the
    particles moves the RMSE by more than 2 % is scored with more). Rows whose mean is
    not finite (a diverged trajectory) are left out, and so are cells whose data come
    from a plant unlike the model the particle filter is given (``mismatch``): there it
    is no limit."""
    ours = summary[(summary["status"] == "ok") & ~summary["estimator"].str.startswith(PAPER_PREFIX)]
    finite = ours[np.isfinite(ours["rmse_mean"]) & _nominal_plant(ours)]
    least = particle_count(LIMIT)

    def rank(row: str) -> float:
        """How well ``row`` stands for the limit: NaN if it cannot."""
        if row == TRUTH_LIMIT:
            return math.inf
        count = particle_count(row)
        return count if count is not None and count >= least else math.nan

    ranks = {row: rank(row) for row in finite["estimator"].unique()}
    ranked = finite.assign(rank=finite["estimator"].map(ranks)).dropna(subset=["rank"])
    chosen = ranked.sort_values("rank").groupby(["system", "regime"]).last()
    return chosen.rename(columns={"estimator": "row", "rmse_mean": "rmse"})[["row", "rmse"]]


LIMIT_COLUMNS = {
    "system": "System",
    "regime": "Regime",
    "limit_row": "Limit row",
    "limit_rmse": "Limit RMSE",
    "best_model_based": "Best model-based",
    "best_model_based_ratio": "Best model-based / limit",
    "best_learned": "Best learned",
    "best_learned_ratio": "Best learned / limit",
}
HEADROOM = 1.3
"""A cell has headroom when the best model-based row is at least this many times the
limit (protocol 7.6): there a better observer is measurably possible."""


def family_rows(summary: pd.DataFrame, family: str) -> list[str]:
    """The rows of ``summary`` (not the paper's) whose family is ``family``."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    return list(dict.fromkeys(ours.loc[families.of_rows(ours) == family, "estimator"]))


def _best(ok: pd.Series, rows: list[str], system: str, regime: str) -> tuple[str, float]:
    """The row of ``rows`` with the lowest finite mean RMSE in the cell, and that RMSE
    (``("", nan)`` if none scored one)."""
    scored = {r: ok[(r, system, regime)] for r in rows if (r, system, regime) in ok}
    finite = {r: value for r, value in scored.items() if math.isfinite(value)}
    if not finite:
        return "", math.nan
    best = min(finite, key=finite.get)
    return best, finite[best]


def limit_frame(summary: pd.DataFrame) -> pd.DataFrame:
    """Per cell: the limit row (:func:`limit_rows`) and its RMSE, the posterior mean under
    the exact model and the least any estimator can expect, and the best model-based and
    the best learned row (families, :mod:`kkl_bench.families`) with their RMSE over it
    (:data:`LIMIT_COLUMNS`). Empty without particle-filter results."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    ok = ours[ours["status"] == "ok"].set_index(["estimator", "system", "regime"])["rmse_mean"]
    model_based, learned = family_rows(ours, "model-based"), family_rows(ours, "learned")
    limits = limit_rows(summary)
    rows = []
    for system in in_paper_order(ours["system"], SYSTEM_TITLES):
        for regime in task_order(ours):
            if (system, regime) not in limits.index:
                continue
            limit_row, limit = limits.loc[(system, regime)]
            filter_row, filter_rmse = _best(ok, model_based, system, regime)
            learned_row, learned_rmse = _best(ok, learned, system, regime)
            rows.append(
                {
                    "system": system,
                    "regime": regime,
                    "limit_row": limit_row,
                    "limit_rmse": limit,
                    "best_model_based": filter_row,
                    "best_model_based_ratio": filter_rmse / limit,
                    "best_learned": learned_row,
                    "best_learned_ratio": learned_rmse / limit,
                }
            )
    return pd.DataFrame(rows, columns=list(LIMIT_COLUMNS))


def limit_table(summary: pd.DataFrame, id: str = "limit") -> Table | None:
    """:func:`limit_frame` with system and regime titles (None without particle-filter
    results)."""
    frame = limit_frame(summary)
    if frame.empty:
        return None
    frame = frame.assign(
        system=frame["system"].map(lambda s: SYSTEM_TITLES.get(s, s)),
        regime=frame["regime"].map(lambda r: REGIME_TITLES.get(r, r)),
    )
    return Table(frame, LIMIT_COLUMNS, id=id)


def headroom_sentence(summary: pd.DataFrame) -> str:
    """How many of the cells with a limit have headroom (:data:`HEADROOM`), read from
    :func:`limit_frame`; empty without a limit."""
    frame = limit_frame(summary)
    if frame.empty:
        return ""
    ratios = frame["best_model_based_ratio"]
    count = int((ratios >= HEADROOM).sum())
    return (
        f"The best model-based row is at least {HEADROOM:g} times the limit in {count} of "
        f"{len(frame)} cells"
        + (f" (median {ratios.median():.2f} times)." if ratios.notna().any() else ".")
    )


def one_line_answer(summary: pd.DataFrame) -> str:
    """One sentence on a track's results (``summary`` of one track): which row has the
    lowest mean RMSE in how many cells (the limit rows aside), and, where a limit was
    scored, the median over cells of the best model-based and the best learned row's RMSE
    over it. Empty if no row scored."""
    ours = summary[
        ~summary["estimator"].str.startswith(PAPER_PREFIX)
        & (summary["status"] == "ok")
        & (families.of_rows(summary) != "limit")
    ]
    finite = ours[np.isfinite(ours["rmse_mean"])]
    if finite.empty:
        return ""
    best = finite.loc[finite.groupby(["system", "regime"])["rmse_mean"].idxmin()]
    counts = best["estimator"].value_counts()
    cells = finite.groupby(["system", "regime"]).ngroups
    leaders = ", ".join(f"`{row}` in {count}" for row, count in counts.head(3).items())
    text = f"Lowest RMSE of the {cells} cells (the limit aside): {leaders}"
    if len(counts) > 3:
        others = len(counts) - 3
        text += f", {others} other row{'s' if others > 1 else ''} in {int(counts.iloc[3:].sum())}"
    frame = limit_frame(summary)
    if frame.empty:
        return text + "."
    medians = [
        f"the best {family} row {frame[column].median():.2f} times"
        for family, column in (
            ("model-based", "best_model_based_ratio"),
            ("learned", "best_learned_ratio"),
        )
        if frame[column].notna().any()
    ]
    return text + "; median distance to the limit: " + " and ".join(medians) + "."


CALIBRATED = "ukf+logged"
"""The calibrate-then-filter row the learned ``+logged`` rows are compared with."""


def best_against_best(
    summary: pd.DataFrame, first: Collection[str], second: Collection[str], track: str
) -> pd.DataFrame:
    """Per cell of ``track`` (its :func:`~kkl_bench.analysis.summary.summary_table`): the row of
    ``first`` with the lowest mean RMSE against the lowest of ``second``, both among the
    rows with no diverged trajectory; their RMSEs (``rmse_a``, ``rmse_b``), names (``a``,
    ``b``), the ratio, its 90 % interval and the verdict of
    :func:`~kkl_bench.analysis.significance.compare` (``"a lower"``, ``"b lower"``, ``"not
    distinguishable"``). Cells where either side has no such row are left out; empty if
    none is left."""
    ok = summary[(summary["status"] == "ok") & (summary["n_diverged"] == 0)]
    cells = dict(iter(ok.groupby(["system", "regime"])))
    rows = []
    for system in in_paper_order(ok["system"], SYSTEM_TITLES):
        for regime in task_order(ok):
            cell = cells.get((system, regime))
            sides = (
                [] if cell is None else [cell[cell["estimator"].isin(n)] for n in (first, second)]
            )
            if not sides or any(side.empty for side in sides):
                continue
            a, b = (side.loc[side["rmse_mean"].idxmin()] for side in sides)
            result = compare(np.asarray(a["rmse_trajectories"]), np.asarray(b["rmse_trajectories"]))
            rows.append(
                {
                    "condition": condition(track, regime),
                    "cell": f"{SYSTEM_TITLES.get(system, system)} {regime}",
                    "rmse_a": a["rmse_mean"],
                    "rmse_b": b["rmse_mean"],
                    "a": a["estimator"],
                    "b": b["estimator"],
                    **result,
                }
            )
    return pd.DataFrame(rows)


def calibrated_versus_learned(summary: pd.DataFrame, track: str) -> pd.DataFrame:
    """:func:`best_against_best` of the calibrated UKF (:data:`CALIBRATED`, ``a``) and the
    learned ``+logged`` rows (``b``): ``"a lower"`` means calibrate-then-filter is lower."""
    learned = [name for name in family_rows(summary, "learned") if name.endswith(variants.LOGGED)]
    return best_against_best(summary, [CALIBRATED], learned, track)


def learned_versus_model_based(summary: pd.DataFrame, track: str) -> pd.DataFrame:
    """:func:`best_against_best` of the learned rows (``a``) and the model-based rows
    (``b``), by their families (:mod:`kkl_bench.families`): ``"a lower"`` means a learned
    row beats every model-based row that did not diverge."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    return best_against_best(
        ours, family_rows(ours, "learned"), family_rows(ours, "model-based"), track
    )
