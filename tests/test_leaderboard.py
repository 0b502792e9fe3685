"""Leaderboard tables from a hand-made summary."""

import math

import pandas as pd
import pytest

from kkl_bench.leaderboard import paper_results, render, summary_table


def results_frame():
    rows = []
    for estimator, rmse in (("good", [0.1, 0.3]), ("bad", [1.0, 3.0]), ("broken", [0.1, math.inf])):
        for system in ("vdp", "duffing"):
            rows.append(
                dict(
                    estimator=estimator,
                    system=system,
                    regime="zero",
                    task=f"{system}/zero@v1",
                    protocol="v1+E1",
                    status="ok",
                    rmse=rmse,
                    smape=[10.0, 30.0],
                    nrmse=[1.0, 1.0],
                    fit_time_s=1.0,
                    estimate_us_per_step=2.0,
                )
            )
    return pd.DataFrame(rows)


def test_summary_pools_trajectories_and_counts_divergence():
    summary = summary_table(results_frame()).set_index(["estimator", "system"])
    assert summary.loc[("good", "vdp"), "rmse_mean"] == pytest.approx(0.2)
    assert summary.loc[("good", "vdp"), "smape_mean"] == pytest.approx(20.0)
    assert summary.loc[("broken", "vdp"), "n_diverged"] == 1


def test_markdown_marks_the_best_and_shows_divergence_in_paper_order():
    text = render(summary_table(results_frame()), "markdown")
    header = text.splitlines()[0]
    assert header.index("Duffing Zero") < header.index("Van der Pol Zero")
    assert "| good        | **0.2** (20)   |" in text
    assert "| bad         | 2 (20)         |" in text
    assert "diverged (1/2)" in text


def test_latex_uses_booktabs_and_bold():
    text = render(summary_table(results_frame()), "latex")
    assert r"\toprule" in text and r"\midrule" in text and r"\bottomrule" in text
    assert r"\textbf{0.2} (20)" in text and r"\hline" not in text


def test_csv_is_the_tidy_summary():
    text = render(summary_table(results_frame()), "csv")
    assert text.splitlines()[0].startswith(
        "estimator,system,regime,status,n_test,n_diverged,rmse_mean"
    )
    assert len(text.splitlines()) == 1 + 6


def test_paper_rows_are_the_papers_numbers():
    paper = paper_results()
    assert len(paper) == 64
    summary = summary_table(results_frame(), with_paper=True)
    row = summary[
        (summary.estimator == "paper:dynamic_hyperkkl")
        & (summary.system == "lorenz")
        & (summary.regime == "zero")
    ]
    assert row["rmse_mean"].item() == 6.67 and row["smape_mean"].item() == 22


def test_unknown_format_lists_the_valid_ones():
    with pytest.raises(
        ValueError, match="unknown format 'html'; valid formats: markdown, latex, csv"
    ):
        render(summary_table(results_frame()), "html")
