"""The leaderboard as text: Markdown tables, LaTeX (booktabs) tabulars or the tidy CSV
(``kkl-bench leaderboard --format``, the board's ``.tex`` and ``.csv`` files)."""

from __future__ import annotations

import pandas as pd
from tabulate import tabulate

from kkl_bench.analysis.leaderboard import MARKUP, _grid, _system_groups, grid_tables
from kkl_bench.report import markdown
from kkl_bench.report.formats import FORMATS


def render(
    summary: pd.DataFrame,
    fmt: str = "markdown",
    systems_per_table: int | None = None,
    settling: bool = False,
) -> str:
    """The leaderboard of ``summary`` (from :func:`~kkl_bench.analysis.summary.summary_table`, one
    track) as text.

    ``fmt`` is ``"markdown"`` (GitHub tables, :func:`grid_tables`), ``"latex"`` (booktabs
    tabulars) or ``"csv"`` (the summary itself, one row per estimator x cell).
    ``settling`` adds the settling-time columns.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; valid formats: {', '.join(FORMATS)}")
    if summary.empty:
        raise ValueError("no results to tabulate")
    if fmt == "csv":
        return summary.drop(columns="rmse_trajectories", errors="ignore").to_csv(
            index=False, float_format="%.6g"
        )
    if fmt == "markdown":
        tables = grid_tables(summary, settling, systems_per_table)
        return "\n\n".join(map(markdown.table, tables)) + "\n"
    groups, regimes = _system_groups(summary, settling, systems_per_table)
    latex = []
    for group in groups:
        header, rows, _, _ = _grid(
            summary, group, regimes, MARKUP["latex"], _latex_escape, settling=settling
        )
        table = tabulate(rows, headers=header, tablefmt="latex_raw", disable_numparse=True)
        latex.append(_booktabs(table))
    return "\n\n".join(latex) + "\n"


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
