"""The paper's findings re-tested: claims, outcomes and their tally on hand-made results."""

import re

import numpy as np
import pandas as pd

from kkl_bench.analysis import findings
from kkl_bench.analysis.findings import Claim, claim_frame, tally
from kkl_bench.analysis.significance import compare
from kkl_bench.analysis.summary import summary_table
from kkl_bench.report import markdown
from kkl_bench.report.board import Board, finding_sections

BASE = np.linspace(0.1, 0.4, 8)


def results(rmse_of):
    """Cells of every (estimator, system, regime) in ``rmse_of``: per-trajectory RMSE of
    two seeds (the second 5 % higher)."""
    rows = []
    for (estimator, system, regime), rmse in rmse_of.items():
        for seed, scale in enumerate((1.0, 1.05)):
            rows.append(
                dict(
                    estimator=estimator,
                    system=system,
                    regime=regime,
                    seed=seed,
                    task=f"{system}/{regime}@v1",
                    protocol="v1+E1",
                    status="ok",
                    rmse=list(rmse * scale),
                    smape=[10.0] * len(rmse),
                    nrmse=[1.0] * len(rmse),
                    fit_time_s=1.0,
                    estimate_us_per_step=1.0,
                )
            )
    return pd.DataFrame(rows)


def test_a_cell_supports_contradicts_or_leaves_a_claim_undecided():
    summary = summary_table(
        results(
            {
                ("lower", "duffing", "sinusoid"): BASE,
                ("higher", "duffing", "sinusoid"): 2 * BASE,  # claim holds
                ("lower", "vdp", "sinusoid"): 3 * BASE,
                ("higher", "vdp", "sinusoid"): BASE,  # claim reversed
                ("lower", "rossler", "sinusoid"): BASE,
                ("higher", "rossler", "sinusoid"): BASE[::-1],  # same mean: undecided
                ("lower", "lorenz", "sinusoid"): BASE,  # outside the claim's systems
                ("higher", "lorenz", "sinusoid"): 9 * BASE,
            }
        )
    )
    frame = claim_frame(
        summary, Claim("lower", "higher", ("duffing", "vdp", "rossler"), ("sinusoid",))
    )
    assert list(frame["system"]) == ["duffing", "vdp", "rossler"]
    assert list(frame["outcome"]) == ["supports", "contradicts", "undecided"]
    assert tally(frame) == "supports in 1 of 3 cells, contradicts in 1, undecided in 1"
    duffing = frame.iloc[0]
    expected = compare(np.array([BASE, 1.05 * BASE]), np.array([2 * BASE, 2.1 * BASE]))
    assert np.isclose(duffing["ratio"], 0.5) and np.isclose(duffing["low"], expected["low"])


def test_the_markdown_shows_only_claims_whose_estimators_have_results():
    cells = {
        (estimator, "lorenz", regime): BASE * factor
        for estimator, factor in (("autonomous_kkl", 1.0), ("dynamic_hyperkkl", 1.5))
        for regime in findings.FORCED
    }
    text = findings_markdown(summary_table(results(cells)))
    assert "### On Lorenz the autonomous observer is best" in text
    assert (
        "`autonomous_kkl` lower than `dynamic_hyperkkl`: **supports in 3 of 3 cells, "
        "contradicts in 0, undecided in 0**" in text
    )
    assert re.search(r"\| Lorenz Sin +\| 0\.256 +\| 0\.384 +\| 0\.667 +\|", text)
    # no curriculum or static results, and no oscillator or Rossler cells: nothing else
    assert "curriculum_kkl" not in text and "static_hyperkkl" not in text
    assert "helps on the oscillators" not in text


def findings_markdown(summary) -> str:
    """The findings' sections of a board of ``summary``, as Markdown."""
    board = Board(summary, pd.DataFrame(), "standard", [], None, None, {}, "results", False, 0.01)
    return "\n\n".join(map(markdown.section, finding_sections(board)[1:]))  # after the guide
