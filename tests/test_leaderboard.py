"""Leaderboard tables from a hand-made summary."""

import math
import re

import numpy as np
import pandas as pd
import pytest

from kkl_bench.analysis import comparisons
from kkl_bench.analysis.comparisons import limit_frame
from kkl_bench.analysis.leaderboard import cost_table, grid_tables, track_summary_table
from kkl_bench.analysis.significance import (
    SEED,
    mark_column,
    per_seed_means,
    ratio_lower_bound,
    resampled_ratios,
)
from kkl_bench.analysis.summary import (
    paper_results,
    summary_table,
    track_summary,
    unsupported_reasons,
)
from kkl_bench.report import html
from kkl_bench.report.markdown import table
from kkl_bench.report.text import render


def results_frame(entries=(("good", [0.1, 0.3]), ("bad", [1.0, 3.0]), ("broken", [0.1, math.inf]))):
    """Cells of ``(estimator, per-trajectory RMSE)`` entries on two systems; one seed each,
    or several when an entry's RMSE is a list of lists (one per seed)."""
    rows = []
    for estimator, rmse in entries:
        by_seed = rmse if isinstance(rmse[0], list) else [rmse]
        for seed, values in enumerate(by_seed):
            for system in ("vdp", "duffing"):
                rows.append(
                    dict(
                        estimator=estimator,
                        system=system,
                        regime="zero",
                        seed=seed,
                        task=f"{system}/zero@v1",
                        protocol="v1+E1",
                        status="ok",
                        rmse=values,
                        smape=[20.0 * (1 + seed)] * len(values),
                        nrmse=[1.0] * len(values),
                        fit_time_s=1.0,
                        estimate_us_per_step=2.0,
                    )
                )
    return pd.DataFrame(rows)


def row_of(text, estimator):
    return next(line for line in text.splitlines() if line.startswith(f"| {estimator} "))


def test_summary_pools_trajectories_and_counts_divergence():
    summary = summary_table(results_frame()).set_index(["estimator", "system"])
    assert summary.loc[("good", "vdp"), "rmse_mean"] == pytest.approx(0.2)
    assert summary.loc[("good", "vdp"), "smape_mean"] == pytest.approx(20.0)
    assert summary.loc[("broken", "vdp"), "n_diverged"] == 1


def test_markdown_marks_the_best_and_shows_divergence_in_paper_order():
    text = render(summary_table(results_frame()), "markdown")
    header = text.splitlines()[0]
    assert header.index("Seeds") < header.index("Duffing Zero") < header.index("Van der Pol Zero")
    assert "| **0.2** (20) " in row_of(text, "good")
    assert "| 2 (20) " in row_of(text, "bad")
    assert "diverged (1/2)" in row_of(text, "broken")


def test_seeds_are_aggregated_as_mean_and_spread_of_the_per_seed_means():
    frame = results_frame((("seeded", [[0.1, 0.3], [0.3, 0.5], [0.5, 0.7]]),))
    summary = summary_table(frame).set_index(["estimator", "system"])
    row = summary.loc[("seeded", "vdp")]
    assert row["n_seeds"] == 3 and row["n_test"] == 2
    assert row["rmse_mean"] == pytest.approx(0.4)  # per-seed means 0.2, 0.4, 0.6
    assert row["rmse_seed_std"] == pytest.approx(0.2)  # sample standard deviation
    assert row["smape_mean"] == pytest.approx(40.0) and row["smape_seed_std"] == pytest.approx(20.0)
    text = render(summary_table(frame), "markdown")
    assert "| 3 " in row_of(text, "seeded") and "| 0.4 ± 0.2 (40) " in text  # alone: unmarked


def test_entries_a_reseed_could_reorder_are_tied_not_bold():
    close = results_frame(
        (
            ("first", [[0.10, 0.20, 0.30, 0.40], [0.12, 0.22, 0.32, 0.42]]),
            ("second", [[0.11, 0.21, 0.31, 0.41], [0.11, 0.21, 0.31, 0.41]]),
            ("far", [[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0]]),
        )
    )
    text = render(summary_table(close), "markdown")
    assert "| *0.26* ± 0.014 (30) " in row_of(text, "first")
    assert "| *0.26* ± 0 (30) " in row_of(text, "second")
    assert "**" not in text and "*2.5*" not in row_of(text, "far")


def test_latex_uses_booktabs_and_bold():
    text = render(summary_table(results_frame()), "latex")
    assert r"\toprule" in text and r"\midrule" in text and r"\bottomrule" in text
    assert r"\textbf{0.2} (20)" in text and r"\hline" not in text


def test_csv_is_the_tidy_summary():
    text = render(summary_table(results_frame()), "csv")
    assert text.splitlines()[0].startswith(
        "estimator,family,system,regime,status,n_seeds,n_test,n_diverged,rmse_mean,rmse_seed_std"
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


def test_bootstrap_bound_of_a_constant_ratio_is_that_ratio():
    best = np.array([[0.1, 0.2, 0.4]])
    assert ratio_lower_bound(3 * best, best) == pytest.approx(3.0)
    assert ratio_lower_bound(best, best) == pytest.approx(1.0)


def test_the_bootstrap_draws_trajectories_then_each_sides_seeds_from_its_seed():
    """The documented resampling, written out: one generator seeded with ``SEED`` draws the
    shared trajectory indices, then the other entry's seeds, then the best's; a column's
    comparisons reuse those draws and the best's per-seed means, with the same numbers."""
    rng = np.random.default_rng(SEED)
    other, best = rng.lognormal(size=(2, 7)), rng.lognormal(size=(3, 7))
    draws = np.random.default_rng(SEED)
    trajectories = draws.integers(7, size=(50, 7))
    other_seeds, best_seeds = draws.integers(2, size=(50, 2)), draws.integers(3, size=(50, 3))

    def means(rmse, seeds):
        per_seed = rmse[:, trajectories].mean(axis=-1)  # (n_seeds, n_resamples)
        return per_seed[seeds, np.arange(50)[:, None]].mean(axis=1)

    expected = means(other, other_seeds) / means(best, best_seeds)
    np.testing.assert_array_equal(resampled_ratios(other, best, 50), expected)
    np.testing.assert_array_equal(resampled_ratios(other, best, 50), expected)  # drawn once
    shared = per_seed_means(best, trajectories)
    np.testing.assert_array_equal(resampled_ratios(other, best, 50, shared), expected)


def test_seed_spread_alone_can_make_a_paired_win_a_tie():
    trajectories = np.linspace(0.1, 1.0, 20)
    steady = np.stack([trajectories] * 3)  # always 10 % better on every trajectory ...
    worse = 1.1 * steady
    assert mark_column({"a": steady, "b": worse}) == {"a": "best", "b": ""}
    # ... but if a's seeds spread from 0.7x to 1.3x, three seeds cannot tell them apart
    spread = np.stack([0.7 * trajectories, trajectories, 1.3 * trajectories])
    assert mark_column({"a": spread * 0.99, "b": worse}) == {"a": "tied", "b": "tied"}
    assert mark_column({"a": steady, "b": worse, "c": np.array([[np.inf] * 20])})["c"] == ""


def test_a_lead_within_the_margin_is_a_tie_however_consistent():
    trajectories = np.linspace(0.1, 1.0, 20)[None]
    # 1e-12 relative on every trajectory: a plain paired bootstrap would call it a win
    assert ratio_lower_bound(trajectories * (1 + 1e-12), trajectories) > 1
    assert mark_column({"a": trajectories, "b": trajectories * (1 + 1e-12)}) == {
        "a": "tied",
        "b": "tied",
    }
    # 0.5 % on every trajectory is within the default 1 % margin, 2 % is not
    assert mark_column({"a": trajectories, "b": 1.005 * trajectories})["a"] == "tied"
    assert mark_column({"a": trajectories, "b": 1.02 * trajectories}) == {"a": "best", "b": ""}
    assert mark_column({"a": trajectories, "b": 1.005 * trajectories}, margin=0.0)["a"] == "best"
    with pytest.raises(ValueError, match=r"margin must be >= 0, got -0\.1"):
        mark_column({"a": trajectories}, margin=-0.1)


def test_comparison_gives_the_ratio_its_interval_and_a_verdict():
    frame = results_frame(
        (
            ("low", [[0.1, 0.2, 0.3, 0.4]] * 2),
            ("high", [[0.2, 0.4, 0.6, 0.8]] * 2),
            ("same", [[0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 0.3, 0.4]]),
        )
    )
    summary = summary_table(frame)
    text = comparison_table(summary, "low", "high")
    duffing = next(line for line in text.splitlines() if line.startswith("| Duffing Zero "))
    assert [cell.strip() for cell in duffing.strip("|").split("|")] == [
        "Duffing Zero",
        "0.25",
        "0.5",
        "0.5",
        "[0.5, 0.5]",
        "low lower",
    ]
    assert "not distinguishable" in comparison_table(summary, "low", "same")
    with_diverged = summary_table(
        results_frame((("low", [[0.1, 0.2]]), ("lost", [[0.1, math.inf]])))
    )
    lost = next(
        line
        for line in comparison_table(with_diverged, "low", "lost").splitlines()
        if line.startswith("| Duffing Zero ")
    )
    assert [cell.strip() for cell in lost.strip("|").split("|")][3:] == [
        "0",
        "a trajectory diverged",
        "diverged",
    ]
    with pytest.raises(
        ValueError, match="no results for 'nobody'; estimators in the results: high, low, same"
    ):
        comparison_table(summary, "low", "nobody")


def test_track_summary_divides_by_the_reference_regime_of_the_paper_track():
    paper = results_frame((("a", [0.1, 0.3]),)).assign(track="paper", regime="sinusoid")
    chirp = results_frame((("a", [0.4, 0.4]),)).assign(track="ood-inputs", regime="chirp")
    far = results_frame((("a", [0.2, math.inf]),)).assign(track="far-init", regime="sinusoid")
    other_systems = results_frame((("a", [0.2, 0.2]),)).assign(
        track="more-systems", regime="sinusoid", system="chua"
    )
    frame = track_summary(pd.concat([paper, chirp, far, other_systems], ignore_index=True))
    assert list(frame["track"]) == ["ood-inputs", "far-init"]  # nothing to compare chua with
    ratios = frame.set_index("track")
    assert ratios.loc["ood-inputs", "ratio"] == pytest.approx(2.0)  # 0.4 / 0.2 on both systems
    assert ratios.loc["far-init", "ratio"] == pytest.approx(1.0)  # 0.2 over the finite one
    assert (ratios.loc["far-init", "n_diverged"], ratios.loc["far-init", "n_trajectories"]) == (
        2,
        4,
    )
    text = render_track_summary(frame)
    assert re.search(r"\| a +\| 2x \(median 2x\) +\| 1x \(median 1x\) \(2/4 diverged\) \|", text)


def test_track_summary_by_condition_groups_the_tasks_that_change_the_same_thing():
    def cells(estimator, track, regime, rmse):
        return results_frame(((estimator, rmse),)).assign(track=track, regime=regime)

    frame = pd.concat(
        [
            cells("a", "paper", "sinusoid", [0.1, 0.1]),
            cells("a", "paper", "square", [0.2, 0.2]),
            cells("a", "mismatch", "params10-sinusoid", [0.2, 0.2]),  # 2x
            cells("a", "mismatch", "params10-square", [0.8, 0.8]),  # 4x
            cells("a", "mismatch", "sensor-square", [0.2, 0.2]),  # 1x
            cells("a+logged", "mismatch", "params10-square", [0.1, 0.1]),  # 0.5x of a's fit
        ],
        ignore_index=True,
    )
    by_condition = track_summary(frame, by_condition=True).set_index(["estimator", "condition"])
    assert by_condition.loc[("a", "params10"), "ratio"] == pytest.approx(math.sqrt(2 * 4))
    assert by_condition.loc[("a", "params10"), "n_cells"] == 4  # two tasks on two systems
    assert by_condition.loc[("a", "params10"), "median"] == pytest.approx(3.0)  # of 2, 2, 4, 4
    assert by_condition.loc[("a", "sensor"), "ratio"] == pytest.approx(1.0)
    assert by_condition.loc[("a+logged", "params10"), "ratio"] == pytest.approx(0.5)
    overall = track_summary(frame).set_index("estimator")
    assert overall.loc["a", "ratio"] == pytest.approx((2 * 4 * 1) ** (1 / 3))
    text = render_track_summary(track_summary(frame, by_condition=True), "condition")
    assert [cell.strip() for cell in text.splitlines()[0].split("|")[2:4]] == ["params10", "sensor"]
    assert re.search(r"\| a\+logged +\| 0\.5x \(median 0\.5x\) +\| - +\|", text)


def test_the_converged_column_gives_each_rows_worst_verdict_over_the_tables_systems():
    falling = {
        "spent": {"phase": {"steps": 8}},
        "log": {"validation_curve": [[0, 2], [4, 1], [8, 0.5]]},
    }
    flat = {"spent": {"phase": {"steps": 8}}, "log": {"validation_curve": [[0, 2], [4, 1], [8, 1]]}}
    frame = results_frame((("learned", [0.1, 0.3]), ("filter", [0.2, 0.2])))
    learned = frame["estimator"] == "learned"
    frame["fit_report"] = [
        (falling if system == "duffing" else flat) if is_learned else {}
        for system, is_learned in zip(frame["system"], learned, strict=True)
    ]
    summary = summary_table(frame)
    both = render(summary, "markdown")
    assert both.splitlines()[0].split("|")[3].strip() == "Converged"
    assert row_of(both, "learned").split("|")[3].strip() == "no"  # Duffing's curve still fell
    assert row_of(both, "filter").split("|")[3].strip() == ""  # trains nothing
    one_per_table = render(summary, "markdown", systems_per_table=1)
    duffing, vdp = one_per_table.split("\n\n")[:2]
    assert row_of(duffing, "learned").split("|")[3].strip() == "no"
    assert row_of(vdp, "learned").split("|")[3].strip() == "yes"
    untrained = summary_table(frame.drop(columns="fit_report"))
    assert "Converged" not in render(untrained, "markdown")
    with_paper = pd.concat(
        [untrained, pd.DataFrame([{"estimator": "paper: x", "converged": None}])]
    )
    assert "Converged" not in render(with_paper.iloc[[0, -1]], "markdown")


def test_settling_columns_follow_each_rmse_column():
    frame = results_frame((("a", [0.1, 0.3, 0.2]), ("b", [0.2, 0.2, 0.2]))).assign(
        track="far-init",
        settling_time_s=[[1.0, 3.0, 2.0]] * 2 + [[0.5, 0.7, math.inf]] * 2,
    )
    text = render(summary_table(frame), "markdown", settling=True)
    header = [cell.strip() for cell in text.splitlines()[0].strip("|").split("|")]
    assert header[2:] == ["Duffing Zero", "settle (s)", "Van der Pol Zero", "settle (s)"]
    assert row_of(text, "a").rstrip("| ").endswith("| 2")
    assert "| 0.7 (1/3 never) " in row_of(text, "b")


def test_limit_frame_names_the_best_model_based_and_learned_rows_over_the_limit():
    rows = [
        ("particle_filter", 0.10),
        ("ekf", 0.11),
        ("ukf", 0.105),
        ("enkf", 0.102),
        ("particle_filter[n=100]", 0.09),  # a limit row: neither model-based nor learned
        ("gru_observer", 0.15),
        ("kalmannet", 0.12),
        ("paper:HyperKKL", 0.01),
    ]
    summary = pd.DataFrame(
        [
            {"estimator": e, "system": "vdp", "regime": "sinusoid", "status": "ok", "rmse_mean": r}
            for e, r in rows
        ]
    )
    frame = limit_frame(summary)
    assert frame.to_dict("records") == [
        {
            "system": "vdp",
            "regime": "sinusoid",
            "limit_row": "particle_filter",
            "limit_rmse": 0.10,
            "best_model_based": "enkf",
            "best_model_based_ratio": pytest.approx(1.02),
            "best_learned": "kalmannet",
            "best_learned_ratio": pytest.approx(1.2),
        }
    ]
    assert limit_frame(summary[summary["estimator"] != "particle_filter"]).empty


@pytest.mark.parametrize(
    ("rows", "expected"),
    [
        # the most particles stand for the limit; fewer, or another proposal, do not
        (
            [
                ("particle_filter", 0.10),
                ("particle_filter[n=20000]", 0.08),
                ("particle_filter[n=100]", 0.05),
                ("particle_filter[n=40000,proposal='bootstrap']", 0.07),
            ],
            ("particle_filter[n=20000]", 0.08),
        ),
        # the truth-told filter wins wherever it was scored; a diverged limit is none
        (
            [("particle_filter", 0.10), ("particle_filter+truth", 0.12)],
            ("particle_filter+truth", 0.12),
        ),
        (
            [("particle_filter", 0.10), ("particle_filter[n=20000]", math.inf)],
            ("particle_filter", 0.10),
        ),
        ([("ukf", 0.10), ("particle_filter+logged", 0.09)], None),
    ],
)
def test_limit_rows_pick_the_most_particles_or_the_truth(rows, expected):
    summary = pd.DataFrame(
        [
            {"estimator": e, "system": "vdp", "regime": "sinusoid", "status": "ok", "rmse_mean": r}
            for e, r in rows
        ]
    )
    limits = comparisons.limit_rows(summary)
    if expected is None:
        assert limits.empty
    else:
        assert tuple(limits.loc[("vdp", "sinusoid")]) == expected


def test_learned_versus_model_based_pits_the_best_learned_row_against_the_best_filter():
    """Per cell: the lowest learned row against the lowest model-based row; a diverged row
    is left out, the particle filter (the limit) is neither side, the verdict is the
    paired test's."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0.9, 1.1, size=40)

    def row(estimator, regime, factor, diverged=0, jitter=0.0):
        rmse = factor * base * rng.uniform(1 - jitter, 1 + jitter, size=base.size)
        if diverged:
            rmse = rmse.copy()
            rmse[0] = math.inf
        return {
            "estimator": estimator,
            "track": "hard",
            "system": "vdp",
            "regime": regime,
            "status": "ok",
            "n_diverged": diverged,
            "rmse_mean": float(np.mean(rmse[np.isfinite(rmse)])),
            "rmse_trajectories": rmse[None, :],
        }

    summary = pd.DataFrame(
        [
            row("particle_filter", "sparse-sinusoid", 0.1),
            row("ukf", "sparse-sinusoid", 0.5, diverged=1),
            row("enkf", "sparse-sinusoid", 2.0),
            row("ekf", "sparse-sinusoid", 3.0),
            row("gru_observer", "sparse-sinusoid", 1.0),
            row("kalmannet", "sparse-sinusoid", 1.5),
            row("ukf", "outliers-sinusoid", 1.0),
            row("gru_observer", "outliers-sinusoid", 1.0, jitter=0.3),
            row("ukf", "quantized-sinusoid", 1.0),
        ]
    )
    frame = comparisons.learned_versus_model_based(summary, "hard")
    records = frame[["cell", "a", "b", "verdict"]].to_dict("records")
    assert records == [
        {
            "cell": "Van der Pol sparse-sinusoid",
            "a": "gru_observer",
            "b": "enkf",
            "verdict": "a lower",
        },
        {
            "cell": "Van der Pol outliers-sinusoid",
            "a": "gru_observer",
            "b": "ukf",
            "verdict": "not distinguishable",
        },
    ]
    assert frame["ratio"].iloc[0] == pytest.approx(0.5)


def comparison_table(summary, a, b):
    return table(comparisons.comparison_table(summary, a, b))


def render_track_summary(frame, column="track"):
    return table(track_summary_table(frame, column))


def test_unsupported_reasons_name_each_reason_once_with_its_systems():
    cells = pd.DataFrame(
        [
            ("pf", "lorenz96-n160", "too big: 160"),
            ("pf", "lorenz96-n20", "too big: 20"),
            ("pf", "lorenz96-n20", "too big: 20"),  # another regime
            ("ring", "chua", "no ring"),
            ("ring", "fitzhugh_nagumo", "no ring"),
            ("ring", "lorenz96-n5", None),
        ],
        columns=["estimator", "system", "error"],
    ).assign(status=lambda frame: np.where(frame["error"].isna(), "ok", "unsupported"))
    assert unsupported_reasons(cells) == [
        ("pf", ["lorenz96-n20"], "too big: 20"),
        ("pf", ["lorenz96-n160"], "too big: 160"),
        ("ring", ["fitzhugh_nagumo", "chua"], "no ring"),
    ]


def test_a_row_with_no_cell_in_a_table_is_left_out_of_it():
    frame = results_frame()
    only_vdp = frame[(frame["estimator"] == "good") & (frame["system"] == "vdp")]
    summary = summary_table(pd.concat([frame, only_vdp.assign(estimator="vdp_only")]))
    tables = grid_tables(summary, systems_per_table=1)
    rows = {table.columns["c2"]: list(table.frame["c0"]) for table in tables}
    assert "vdp_only" in rows["Van der Pol Zero"] and "vdp_only" not in rows["Duffing Zero"]


def test_the_cost_table_writes_steps_and_samples_as_counts_and_blank_where_none():
    spent = {
        "phase1": {"steps": 94600, "samples": 134758400, "seconds": 12000.0},
        "phase2": {"steps": 4000, "seconds": 345.4},
    }
    frame = results_frame((("kkl", [0.1, 0.2]), ("ekf", [0.1, 0.2]), ("ring", [0.1, 0.2])))
    frame["fit_report"] = [{"spent": spent} if e == "kkl" else {} for e in frame["estimator"]]
    frame["fit_time_s"] = 0.0005  # the kkl row's is its phases' 12345.4 s
    frame.loc[frame["estimator"] == "ring", "status"] = "unsupported"  # no row: nothing ran
    costs = cost_table(summary_table(frame))
    rows = {
        line.split("|")[1].strip(): [cell.strip() for cell in line.split("|")[3:9]]
        for line in table(costs).splitlines()[2:]
        if "duffing" in line
    }
    assert rows["kkl"][2:6] == ["94,600", "134,758,400", "4,000", ""]
    assert rows["ekf"][2:6] == ["", "", "", ""]
    assert (rows["kkl"][0], rows["ekf"][0]) == ("12,345", "0")  # fit times in whole seconds
    assert set(rows) == {"kkl", "ekf"}
    page = html.table(costs)
    assert ">94,600</td>" in page and 'data-value="Infinity"></td>' in page
