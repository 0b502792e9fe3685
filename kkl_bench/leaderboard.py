"""Leaderboard tables from stored results, in the paper's layout.

Rows are estimators, columns are (system, regime) pairs grouped two systems
per table as in the paper's Tables 1-2, and a cell reads ``RMSE (SMAPE%)``,
the mean over the test trajectories. The best RMSE of each column is marked
(bold). A cell where some trajectory diverged reads ``diverged (k/n)``; a
cell whose estimator failed reads ``error``. The paper's published numbers
can be shown as reference rows. Nothing here recomputes a metric: it reads
what the harness recorded.
"""

from __future__ import annotations

import importlib.resources
import io
import math
from collections.abc import Callable, Sequence

import pandas as pd
from tabulate import tabulate

from kkl_bench.results import mean_and_std

FORMATS = ("markdown", "latex", "csv")
PAPER_PREFIX = "paper:"
SYSTEM_TITLES = {
    "duffing": "Duffing",
    "vdp": "Van der Pol",
    "rossler": "Rossler",
    "lorenz": "Lorenz",
}
REGIME_TITLES = {"zero": "Zero", "constant": "Const", "sinusoid": "Sin", "square": "Sqr"}


def paper_results() -> pd.DataFrame:
    """The HyperKKL paper's Tables 1-2: columns method, system, regime, rmse, smape_percent."""
    text = importlib.resources.files("kkl_bench").joinpath("paper_results.csv").read_text()
    return pd.read_csv(io.StringIO(text))


def summary_table(results: pd.DataFrame, with_paper: bool = False) -> pd.DataFrame:
    """One row per (estimator, system, regime): the numbers every table shows.

    Columns: estimator, system, regime, status, n_test, n_diverged, rmse_mean,
    rmse_std, smape_mean, nrmse_mean, fit_time_s, estimate_us_per_step, task,
    protocol. Several seeds of one cell are pooled.
    """
    columns = ["estimator", "system", "regime"]
    rows = []
    for (estimator, system, regime), cells in results.groupby(columns, sort=False):
        scored = cells[cells["status"] == "ok"]
        rmse = [value for values in scored["rmse"] for value in values]
        rmse_mean, rmse_std = mean_and_std(rmse)
        rows.append(
            {
                "estimator": estimator,
                "system": system,
                "regime": regime,
                "status": "ok" if len(scored) == len(cells) else "error",
                "n_test": len(rmse),
                "n_diverged": sum(not math.isfinite(value) for value in rmse),
                "rmse_mean": rmse_mean,
                "rmse_std": rmse_std,
                "smape_mean": mean_and_std([v for values in scored["smape"] for v in values])[0],
                "nrmse_mean": mean_and_std([v for values in scored["nrmse"] for v in values])[0],
                "fit_time_s": scored["fit_time_s"].mean(),
                "estimate_us_per_step": scored["estimate_us_per_step"].mean(),
                "task": cells["task"].iloc[0],
                "protocol": cells["protocol"].iloc[0],
                **_map_quality(cells),
            }
        )
    summary = pd.DataFrame(rows)
    if with_paper:
        paper = paper_results().rename(columns={"rmse": "rmse_mean", "smape_percent": "smape_mean"})
        paper["estimator"] = PAPER_PREFIX + paper.pop("method")
        paper["status"] = "ok"
        paper["n_diverged"] = 0
        summary = pd.concat([summary, paper], ignore_index=True)
    return summary


MAP_QUALITY = ("reconstruction_rmse_unforced", "reconstruction_rmse_forced", "pde_residual_forced")
"""Map-quality numbers a KKL estimator reports (see :func:`kkl_bench.kkl.autonomous.map_quality`)."""


def _map_quality(cells: pd.DataFrame) -> dict[str, float]:
    """The map-quality numbers in the cells' fit reports (NaN where none are reported)."""
    reports = cells["fit_report"] if "fit_report" in cells else pd.Series([{}] * len(cells))
    quality = next(
        (r["map_quality"] for r in reports if isinstance(r, dict) and "map_quality" in r), {}
    )
    return {key: quality.get(key, math.nan) for key in MAP_QUALITY}


def _format_cell(row: pd.Series, best: bool, bold: tuple[str, str]) -> str:
    if row["status"] != "ok":
        return "error"
    if row["n_diverged"]:
        return f"diverged ({row['n_diverged']}/{row['n_test']})"
    rmse = f"{row['rmse_mean']:.3g}"
    if best:
        rmse = f"{bold[0]}{rmse}{bold[1]}"
    return f"{rmse} ({row['smape_mean']:.3g})"


def _grid(
    summary: pd.DataFrame,
    systems: Sequence[str],
    regimes: Sequence[str],
    bold: tuple[str, str],
    escape: Callable[[str], str] = str,
) -> tuple[list[str], list[list[str]]]:
    """Header and rows of one table over ``systems`` x ``regimes``; ``escape`` quotes labels."""
    estimators = list(dict.fromkeys(summary["estimator"]))
    indexed = summary.set_index(["estimator", "system", "regime"])
    header = ["Estimator"] + [
        escape(f"{SYSTEM_TITLES.get(s, s)} {REGIME_TITLES.get(r, r)}")
        for s in systems
        for r in regimes
    ]
    best = {}
    for system in systems:
        for regime in regimes:
            column = summary[
                (summary["system"] == system)
                & (summary["regime"] == regime)
                & (summary["status"] == "ok")
                & (summary["n_diverged"] == 0)
            ]
            if len(column):
                best[system, regime] = column["rmse_mean"].min()
    rows = []
    for estimator in estimators:
        row = [escape(estimator)]
        for system in systems:
            for regime in regimes:
                key = (estimator, system, regime)
                if key not in indexed.index:
                    row.append("-")
                    continue
                cell = indexed.loc[key]
                row.append(
                    _format_cell(cell, cell["rmse_mean"] == best.get((system, regime)), bold)
                )
        rows.append(row)
    return header, rows


def _in_paper_order(names: pd.Series, known: dict[str, str]) -> list[str]:
    """Distinct ``names``: the paper's ones in its order, then any others sorted."""
    present = set(names)
    return [name for name in known if name in present] + sorted(present - set(known))


def _chunks(items: Sequence[str], size: int) -> list[Sequence[str]]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def render(summary: pd.DataFrame, fmt: str = "markdown", systems_per_table: int = 2) -> str:
    """The leaderboard of ``summary`` (from :func:`summary_table`) as text.

    ``fmt`` is ``"markdown"`` (GitHub tables), ``"latex"`` (booktabs tabulars)
    or ``"csv"`` (the summary itself, one row per estimator x cell).
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; valid formats: {', '.join(FORMATS)}")
    if summary.empty:
        raise ValueError("no results to tabulate")
    if fmt == "csv":
        return summary.to_csv(index=False, float_format="%.6g")
    systems = _in_paper_order(summary["system"], SYSTEM_TITLES)
    regimes = _in_paper_order(summary["regime"], REGIME_TITLES)
    tables = []
    for group in _chunks(systems, systems_per_table):
        if fmt == "markdown":
            header, rows = _grid(summary, group, regimes, ("**", "**"))
            tables.append(tabulate(rows, headers=header, tablefmt="github", disable_numparse=True))
        else:
            header, rows = _grid(summary, group, regimes, (r"\textbf{", "}"), _latex_escape)
            tables.append(
                _booktabs(
                    tabulate(rows, headers=header, tablefmt="latex_raw", disable_numparse=True)
                )
            )
    return "\n\n".join(tables) + "\n"


def _latex_escape(text: str) -> str:
    for character in "&%$#_{}":
        text = text.replace(character, "\\" + character)
    return text


def _booktabs(latex: str) -> str:
    """Turn tabulate's ``latex_raw`` rules (three ``\\hline``) into booktabs rules."""
    rules = iter([r"\toprule", r"\midrule", r"\bottomrule"])
    return "\n".join(
        next(rules) if line.strip() == r"\hline" else line for line in latex.splitlines()
    )


def cost_table(summary: pd.DataFrame) -> str:
    """Markdown table per (estimator, system): fit time, estimation cost, NRMSE and, for
    KKL estimators, the quality of their maps (which bounds what they can reach)."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    grouped = ours.groupby(["estimator", "system"]).agg(
        fit_time_s=("fit_time_s", "mean"),
        estimate_us_per_step=("estimate_us_per_step", "mean"),
        nrmse_mean=("nrmse_mean", "mean"),
        **{key: (key, "first") for key in MAP_QUALITY},
    )
    order = {system: i for i, system in enumerate(_in_paper_order(ours["system"], SYSTEM_TITLES))}
    rows = grouped.reset_index().sort_values(
        ["estimator", "system"], key=lambda c: c.map(order) if c.name == "system" else c
    )
    rows = rows.astype(object).where(rows.notna(), None)
    return tabulate(
        rows,
        headers=[
            "Estimator",
            "System",
            "Fit time (s)",
            "Estimation (µs / trajectory-step)",
            "NRMSE (mean over regimes)",
            "|x - T*(T(x))| unforced",
            "|x - T*(T(x))| forced",
            "PDE residual (rel.) forced",
        ],
        tablefmt="github",
        floatfmt=".3g",
        showindex=False,
        missingval="",
    )
