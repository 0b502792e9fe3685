"""`kkl-bench run`'s estimate: fit times measured from cells, and the plan it prints."""

import math

import pandas as pd

from kkl_bench.cli import main
from kkl_bench.protocol import N_SAMPLES
from kkl_bench.run import fit_times
from kkl_bench.run.results import training_seconds


def cell(estimator, seed, spent_s, us_per_step, status="ok", n_test=5):
    phase = {"steps": 100, "seconds": spent_s / 2}
    report = {"spent": {"phase1": phase, "phase2": phase}}
    return {
        "profile": "quick", "estimator": estimator, "system": "duffing", "seed": seed,
        "status": status, "fit_report": report if spent_s else {}, "fit_time_s": 0.5,
        "estimate_us_per_step": us_per_step, "n_test": n_test,
        "provenance": {"git_commit": "abc"},
    }  # fmt: skip


def test_the_median_fit_and_scoring_times_per_row_and_system():
    cells = pd.DataFrame(
        [
            cell("a", 0, 10.0, 2.0), cell("a", 0, 10.0, 4.0),  # one fit, two cells
            cell("a", 1, 20.0, 2.0), cell("a", 2, 40.0, 2.0),  # three fits: median 20
            cell("b", 0, 0.0, 1.0),  # trains nothing: its fit time
            cell("c", 0, 5.0, 1.0, status="error"),  # left out
        ]
    )  # fmt: skip
    table = fit_times.measure(cells).set_index("estimator")
    assert table.loc["a", "fit_s"] == 20.0 and table.loc["a", "fits"] == 3
    # per fit the median of its cells (3 us, 2, 2), then the median over fits: 2 us
    assert math.isclose(table.loc["a", "score_s_per_cell"], 2e-6 * 5 * N_SAMPLES)
    assert table.loc["b", "fit_s"] == 0.5 and "c" not in table.index
    assert table.loc["a", "scored_at"] == "abc"


def test_an_estimate_adds_fit_and_scoring_and_names_what_it_cannot_estimate():
    table = pd.DataFrame(
        [{"profile": "quick", "estimator": "a", "system": "duffing", "fit_s": 10.0,
          "score_s_per_cell": 0.5, "fits": 1, "scored_at": "abc"}]
    ).set_index(fit_times.KEY)  # fmt: skip
    seconds, unknown = fit_times.estimate([("a", "duffing", 4), ("a", "vdp", 4)], "quick", table)
    assert seconds[0] == 12.0 and math.isnan(seconds[1]) and unknown == ["a on vdp"]


def test_a_run_says_its_profile_and_estimate_before_the_first_fit(tmp_path, capsys):
    argv = ["run", "--estimator", "ekf", "--system", "duffing", "--regime", "zero"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    first = capsys.readouterr().err
    assert "profile quick (the default; --profile to choose); 1 fits of ekf making 1 cells" in first
    argv[-1] = "sinusoid"  # a second run of the same fit: estimated from the first
    assert main([*argv, "--results", str(tmp_path), "--profile", "quick"]) == 0
    second = capsys.readouterr().err
    assert "profile quick; 1 fits of ekf making 1 cells (0 already done); estimated" in second
    assert "(fit times recorded on this profile)" in second


def test_the_shipped_table_covers_the_quick_job_of_the_readme():
    table = fit_times.shipped().set_index(fit_times.KEY)
    for system in ("duffing", "vdp", "rossler", "lorenz"):
        assert ("quick", "dynamic_hyperkkl", system) in table.index


def test_the_bar_counts_every_fit_of_a_system_fitted_per_task(tmp_path, capsys):
    """On the hard track one estimator has a fit per measurement model on one system: the
    bar shares each fit's estimate over its own cells and ends at 100 %."""
    argv = ["run", "--estimator", "ekf", "--system", "duffing", "--track", "hard"]
    regimes = ["--regime", "outliers-sinusoid", "quantized-sinusoid"]
    assert main([*argv, *regimes, "--results", str(tmp_path)]) == 0
    error = capsys.readouterr().err
    assert "2 fits of ekf making 2 cells" in error and "100%" in error


def test_a_training_counts_its_processor_time_on_the_cpu_and_its_wall_time_elsewhere():
    times = {"steps": 10, "seconds": 30.0, "processor_seconds": 12.0}
    assert training_seconds({"spent": {"phase1": {**times, "device": "cpu"}}}) == 12.0
    assert training_seconds({"spent": {"phase1": {**times, "device": "cuda"}}}) == 30.0
    before = {"steps": 10, "seconds": 30.0, "device": "cpu"}  # recorded no processor time
    assert training_seconds({"spent": {"phase1": before, "phase2": {"steps": 0}}}) == 30.0
