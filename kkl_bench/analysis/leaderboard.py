"""The leaderboard's tables, from :func:`~kkl_bench.analysis.summary.summary_table` and friends.

Each function returns a :class:`~kkl_bench.analysis.document.Table`, which the
terminal and the README render as Markdown and the page as HTML
(:mod:`kkl_bench.report`); :func:`render` also writes the paper-layout grid as
LaTeX and the summary as CSV.

The grid is the paper's layout: rows are estimators, columns are (system,
regime) pairs grouped two systems per table as in the paper's Tables 1-2. A
cell reads ``RMSE ± std (SMAPE %)``: for each training seed the mean over the
test trajectories, then the mean of those over the seeds, ``±`` their
standard deviation over the seeds (absent for one seed). The ``Seeds`` column
says how many; ``Converged``, whether the trainings behind the row's cells of the
table converged (protocol section 6.5, the worst verdict of
:func:`~kkl_bench.support.convergence.worst`; empty for rows that do not train). Marks
come from :mod:`kkl_bench.analysis.significance`: **bold** where
the lowest RMSE beats every other entry of its column, *italic* for the
entries tied with the lowest. A cell where some trajectory diverged reads
``diverged (k/n), median m`` (over all seeds, with the median RMSE of all its
trajectories); a cell whose estimator failed reads ``error``. Tracks that
declare it add the settling time beside each RMSE.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from kkl_bench import families
from kkl_bench.analysis.comparisons import limit_rows
from kkl_bench.analysis.document import Table
from kkl_bench.analysis.significance import MARGIN
from kkl_bench.analysis.summary import (
    MAP_QUALITY,
    PAPER_PREFIX,
    REGIME_TITLES,
    SYSTEM_TITLES,
    in_paper_order,
    paper_results,
    task_order,
)
from kkl_bench.support import convergence

MARKUP = {
    "markdown": {"best": ("**", "**"), "tied": ("*", "*")},
    "latex": {"best": (r"\textbf{", "}"), "tied": (r"\textit{", "}")},
}


def _format_cell(row: pd.Series, markup: dict[str, tuple[str, str]]) -> str:
    """``RMSE ± std (SMAPE)``, marked; ``diverged (k/n)``, ``unsupported`` or ``error``
    where it applies."""
    if row["status"] != "ok":
        return "unsupported" if row["status"] == "unsupported" else "error"
    if row["n_diverged"]:
        return (
            f"diverged ({int(row['n_diverged'])}/{int(row['n_test'] * row['n_seeds'])}), "
            f"median {row['rmse_median']:.3g}"
        )
    rmse = f"{row['rmse_mean']:.3g}"
    mark = row.get("mark", "")
    if mark:
        rmse = f"{markup[mark][0]}{rmse}{markup[mark][1]}"
    spread = row.get("rmse_seed_std", math.nan)
    if isinstance(spread, float) and math.isfinite(spread):
        rmse += f" ± {spread:.2g}"
    return f"{rmse} ({row['smape_mean']:.3g})"


def _seeds(rows: pd.DataFrame) -> str:
    """How many seeds an estimator's cells have: ``3``, or ``2-3`` where they differ."""
    counts = rows["n_seeds"].dropna() if "n_seeds" in rows else pd.Series(dtype=float)
    if counts.empty:
        return ""
    low, high = int(counts.min()), int(counts.max())
    return str(low) if low == high else f"{low}-{high}"


def _verdicts(summary: pd.DataFrame, systems: Sequence[str]) -> dict[str, str] | None:
    """Per estimator, the worst convergence verdict of its cells on ``systems``; None when
    no row of ``summary`` trains (or it records no verdicts)."""
    if "converged" not in summary:
        return None
    if not (summary["converged"].fillna(convergence.UNTRAINED) != convergence.UNTRAINED).any():
        return None  # only rows that do not train (the paper's rows record no verdict)
    shown = summary[summary["system"].isin(systems)]
    return shown.groupby("estimator")["converged"].agg(convergence.worst).to_dict()


def _format_settling(row: pd.Series) -> str:
    """Median settling time in s, with how many trajectories never settled."""
    if row["status"] != "ok" or not math.isfinite(row["settling_median_s"]):
        never = row.get("n_unsettled", 0)
        return f"never ({never}/{row['n_test'] * row['n_seeds']})" if never else "-"
    text = f"{row['settling_median_s']:.2g}"
    if row["n_unsettled"]:
        text += f" ({row['n_unsettled']}/{row['n_test'] * row['n_seeds']} never)"
    return text


def _grid(
    summary: pd.DataFrame,
    systems: Sequence[str],
    regimes: Sequence[str],
    markup: dict[str, tuple[str, str]],
    escape: Callable[[str], str] = str,
    settling: bool = False,
) -> tuple[list[str], list[list[str]], list[tuple[str, str] | None], list[str]]:
    """Header, rows, the (system, regime) of each column (None for the others) and the
    results row of each row of one table over ``systems`` x ``regimes``; ``escape`` quotes
    labels. A row is labelled by :func:`~kkl_bench.families.shown_name` (the limit as such).

    With ``settling``, every RMSE column is followed by a settling-time column. A row with
    no cell in the table is left out. The ``Converged`` column is there when some row of
    ``summary`` trains.
    """
    estimators = list(dict.fromkeys(summary["estimator"]))
    shown = families.shown_names(summary)
    indexed = summary.set_index(["estimator", "system", "regime"])
    verdicts = _verdicts(summary, systems)
    header, cells = ["Estimator", "Seeds"], [None, None]
    if verdicts is not None:
        header.append("Converged")
        cells.append(None)
    for system in systems:
        for regime in regimes:
            header.append(
                escape(f"{SYSTEM_TITLES.get(system, system)} {REGIME_TITLES.get(regime, regime)}")
            )
            cells.append((system, regime))
            if settling:
                header.append("settle (s)")
                cells.append(None)
    rows, names = [], []
    for estimator in estimators:
        if not any((estimator, *cell) in indexed.index for cell in cells if cell):
            continue  # no cell in this table (a row run on other systems only)
        own = summary[summary["estimator"] == estimator]
        row = [escape(shown[estimator]), _seeds(own)]
        if verdicts is not None:
            row.append(verdicts.get(estimator, convergence.UNTRAINED))
        for system in systems:
            for regime in regimes:
                key = (estimator, system, regime)
                found = key in indexed.index
                row.append(_format_cell(indexed.loc[key], markup) if found else "-")
                if settling:
                    row.append(_format_settling(indexed.loc[key]) if found else "-")
        rows.append(row)
        names.append(estimator)
    return header, rows, cells, names


def _chunks(items: Sequence[str], size: int) -> list[Sequence[str]]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def _system_groups(summary: pd.DataFrame, settling: bool, systems_per_table: int | None):
    """The systems of each table (as many as keep about eight result columns by default)
    and the regimes of every table."""
    systems = in_paper_order(summary["system"], SYSTEM_TITLES)
    regimes = task_order(summary)
    if systems_per_table is None:
        systems_per_table = max(1, 8 // (len(regimes) * (2 if settling else 1)))
    return _chunks(systems, systems_per_table), regimes


def best_possible(summary: pd.DataFrame) -> pd.Series:
    """Per (system, regime): the Bayes limit's RMSE (:func:`~kkl_bench.analysis.comparisons.limit_rows`)
    where it was scored, else the lowest RMSE of the column's rows (the paper's left out)."""
    ours = summary[(summary["status"] == "ok") & ~summary["estimator"].str.startswith(PAPER_PREFIX)]
    lowest = ours[np.isfinite(ours["rmse_mean"])].groupby(["system", "regime"])["rmse_mean"].min()
    return limit_rows(summary)["rmse"].astype(float).combine_first(lowest)


def grid_tables(
    summary: pd.DataFrame,
    settling: bool = False,
    systems_per_table: int | None = None,
    name: str = "board",
) -> list[Table]:
    """The paper-layout tables of ``summary`` (one track), marks in Markdown syntax, each
    RMSE cell shaded by its ratio to :func:`best_possible` (inf where a trajectory
    diverged); ids ``<name>-0``, ``<name>-1``, ..."""
    if summary.empty:
        raise ValueError("no results to tabulate")
    groups, regimes = _system_groups(summary, settling, systems_per_table)
    best = best_possible(summary)
    indexed = summary.set_index(["estimator", "system", "regime"])
    tables = []
    for number, group in enumerate(groups):
        header, rows, cells, row_names = _grid(
            summary, group, regimes, MARKUP["markdown"], settling=settling
        )
        keys = [f"c{i}" for i in range(len(header))]
        shades = []
        for row_name in row_names:
            shade = []
            for cell in cells:
                key = (row_name, *cell) if cell else None
                ratio = math.nan
                if key in indexed.index and not row_name.startswith(PAPER_PREFIX):
                    entry = indexed.loc[key]
                    if entry["status"] == "ok":
                        ratio = (
                            math.inf
                            if entry["n_diverged"]
                            else entry["rmse_mean"] / best.get(cell, math.nan)
                        )
                shade.append(ratio)
            shades.append(shade)
        tables.append(
            Table(
                pd.DataFrame(rows, columns=keys),
                dict(zip(keys, header, strict=True)),
                id=f"{name}-{number}",
                shades=pd.DataFrame(shades, columns=keys, dtype=float),
            )
        )
    return tables


def caption(track: str, profile: str, smoke: bool, settling: bool = False) -> str:
    """What a printed table is and how to read its cells (Markdown, one paragraph)."""
    kind = " (a smoke test: its numbers say nothing about the methods)" if smoke else ""
    settle = "; `settle (s)`: median settling time" if settling else ""
    return (
        f"Track `{track}`, profile `{profile}`{kind}. A cell reads `RMSE ± std (SMAPE %)`: "
        "the steady-state RMSE, mean over test trajectories and then over the training "
        "seeds (`Seeds`), ± its standard deviation over seeds, and the mean SMAPE in %; "
        f"**bold**: lowest by a paired bootstrap with a {100 * MARGIN:g} % margin, *italics*: "
        f"tied with the lowest{settle}.\n"
    )


COST_COLUMNS = {
    "fit_time_s": "Fit time (s)",
    "estimate_us_per_step": "Estimation (µs / trajectory-step)",
    "phase1_steps": "Phase 1 steps",
    "phase1_samples": "Phase 1 samples",
    "phase2_steps": "2nd phase steps",
    "phase2_samples": "2nd phase samples",
    "converged": "Converged",
    "nrmse_mean": "NRMSE (mean over regimes)",
    "reconstruction_rmse_unforced": "|x - T*(T(x))| unforced",
    "reconstruction_rmse_forced": "|x - T*(T(x))| forced",
    "pde_residual_forced": "PDE residual (rel.) forced",
}
"""The cost table's columns: per (estimator, system), means over regimes and seeds."""


_COST_AGGREGATES = {
    **{key: "first" for key in MAP_QUALITY},
    "converged": convergence.worst,
}


def cost_frame(summary: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, system): costs, training budget spent, NRMSE and map quality; an
    estimator's system where every cell is ``unsupported`` (nothing ran) is left out. Fit
    times are whole seconds, steps and samples counts (``Int64``, missing where none)."""
    ours = summary[
        ~summary["estimator"].str.startswith(PAPER_PREFIX) & (summary["status"] != "unsupported")
    ]
    grouped = ours.groupby(["estimator", "system"]).agg(
        **{
            key: (key, _COST_AGGREGATES.get(key, "first" if "phase" in key else "mean"))
            for key in COST_COLUMNS
        }
    )
    # written as whole numbers: 94,600 steps; a fit of 7,660 s (fit times run from under a
    # second for a filter to hours for a hypernetwork: three digits read as 7.66e+03)
    whole = ["fit_time_s", *(key for key in COST_COLUMNS if key.endswith(("_steps", "_samples")))]
    grouped[whole] = grouped[whole].round().astype("Int64")
    order = {system: i for i, system in enumerate(in_paper_order(ours["system"], SYSTEM_TITLES))}
    return grouped.reset_index().sort_values(
        ["estimator", "system"], key=lambda c: c.map(order) if c.name == "system" else c
    )


def cost_table(summary: pd.DataFrame) -> Table:
    """Per (estimator, system): fit time, estimation cost, the optimizer steps and samples
    of Phase 1 (shared by the KKL rows of a system) and of the estimator's own second
    phase, NRMSE and, for KKL estimators, the quality of their maps."""
    columns = {"estimator": "Estimator", "system": "System", **COST_COLUMNS}
    return Table(cost_frame(summary), columns, id="costs", intfmt=",", sortable=True)


def measured_cost_table(costs: pd.DataFrame) -> Table:
    """A ``kkl-bench cost`` measurement (:mod:`kkl_bench.analysis.cost`): per estimator, the µs per
    trajectory-step on each system (mean over its tasks), the largest over all cells, and
    how many times cheaper than the EKF it is on average: per system, the mean of the
    EKF's costs timed in each row's own run over the mean of the row's, averaged over the
    systems. Where the measurement has them: the engine timed, the reference engine's cost
    beside a compiled one, the flops of a trajectory-step and the cost over the floor they
    imply (means over the row's cells)."""
    means = costs.groupby(["estimator", "system"])[
        ["us_per_trajectory_step", "reference_us_per_trajectory_step"]
    ].mean()
    per_system = means["us_per_trajectory_step"].unstack("system")
    systems = in_paper_order(per_system.columns, SYSTEM_TITLES)
    table = per_system[systems].rename(columns=lambda name: SYSTEM_TITLES.get(name, name))
    table["largest cell"] = costs.groupby("estimator")["us_per_trajectory_step"].max()
    ratios = (means["reference_us_per_trajectory_step"] / means["us_per_trajectory_step"]).unstack(
        "system"
    )
    table["EKF / this (mean over systems)"] = ratios[systems].mean(axis=1)
    if "engine" in costs and costs["engine"].notna().any():
        rows = costs.groupby("estimator")
        table["engine"] = rows["engine"].agg(lambda e: ", ".join(sorted(set(e.dropna()))))
        table["reference engine (µs, mean)"] = rows[
            "reference_engine_us_per_trajectory_step"
        ].mean()
        table["flops / step (mean)"] = rows["flops_per_trajectory_step"].mean()
        table["cost / floor (mean)"] = rows["over_floor"].mean()
    frame = table.reset_index()
    headers = {"estimator": "Estimator (µs / trajectory-step)"}
    return Table(frame, headers | {c: c for c in table.columns}, id="measured-costs")


def paper_comparison(summary: pd.DataFrame) -> Table:
    """Our RMSE over the paper's for each of the paper's methods and cells."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)].set_index(
        ["estimator", "system", "regime"]
    )
    paper = paper_results()
    systems = in_paper_order(paper["system"], SYSTEM_TITLES)
    regimes = in_paper_order(paper["regime"], REGIME_TITLES)
    columns = {"method": "Method (ours / paper)"} | {
        f"{s}/{r}": f"{SYSTEM_TITLES[s]} {REGIME_TITLES[r]}" for s in systems for r in regimes
    }
    rows = []
    for method, theirs in paper.groupby("method", sort=False):
        theirs = theirs.set_index(["system", "regime"])["rmse"]
        row = {"method": method}
        for system in systems:
            for regime in regimes:
                key = (method, system, regime)
                ratio = (
                    ours.loc[key, "rmse_mean"] / theirs[system, regime]
                    if key in ours.index
                    else None
                )
                row[f"{system}/{regime}"] = (
                    "-"
                    if ratio is None
                    else f"{ratio:.2g}x"
                    if math.isfinite(ratio)
                    else "diverged"
                )
        rows.append(row)
    return Table(pd.DataFrame(rows, columns=list(columns)), columns, id="paper-ratios")


def track_summary_table(frame: pd.DataFrame, column: str = "track", id: str = "") -> Table:
    """Estimators as rows, the values of ``column`` (``track``, or ``condition`` for one
    track's :func:`~kkl_bench.analysis.summary.track_summary` by condition) as columns, ``ratio``
    with the median of the cells' ratios (and diverged counts)."""
    headers = list(dict.fromkeys(frame[column]))
    indexed = frame.set_index(["estimator", column])
    rows = []
    for estimator in dict.fromkeys(frame["estimator"]):
        row = [estimator]
        for header in headers:
            if (estimator, header) not in indexed.index:
                row.append("-")
                continue
            cell = indexed.loc[(estimator, header)]
            text = "-"
            if math.isfinite(cell["ratio"]):
                text = f"{cell['ratio']:.3g}x (median {cell['median']:.3g}x)"
            if cell["n_diverged"]:
                text += f" ({int(cell['n_diverged'])}/{int(cell['n_trajectories'])} diverged)"
            row.append(text)
        rows.append(row)
    keys = ["estimator", *(f"c{i}" for i in range(len(headers)))]
    columns = dict(zip(keys, ["Estimator", *headers], strict=True))
    return Table(pd.DataFrame(rows, columns=keys), columns, id=id)
