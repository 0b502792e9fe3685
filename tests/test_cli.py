"""The command line: smoke runs, the leaderboard, and clear errors on bad input."""

import pytest

from kkl_bench.cli import main


def test_run_then_leaderboard(tmp_path, capsys):
    results = str(tmp_path / "results")
    args = [
        "run",
        "--estimator",
        "ekf",
        "--system",
        "vdp",
        "--regime",
        "zero",
        "square",
        "--results",
        results,
    ]
    assert main(args) == 0
    assert "2 cells scored, 0 already done, 0 failed" in capsys.readouterr().out
    assert main(args) == 0
    assert "0 cells scored, 2 already done" in capsys.readouterr().out
    assert main(["leaderboard", "--results", results, "--details"]) == 0
    table = capsys.readouterr().out
    assert "| Estimator   | System   |   Fit time (s) |" in table
    assert "| Estimator   | Van der Pol Zero   | Van der Pol Sqr   |" in table
    board, details = table.split("\n\n")
    assert board.count("| ekf ") == 1 and details.count("| ekf ") == 1
    assert main(["leaderboard", "--results", results, "--format", "latex", "--with-paper"]) == 0
    latex = capsys.readouterr().out
    assert r"paper:static\_hyperkkl" in latex and r"\toprule" in latex


@pytest.mark.slow
def test_quick_profile_for_both_filters_fills_all_sixteen_cells(tmp_path, capsys):
    results = str(tmp_path)
    assert (
        main(["run", "--estimator", "ekf", "ukf", "--profile", "quick", "--results", results]) == 0
    )
    capsys.readouterr()
    assert main(["leaderboard", "--results", results, "--format", "csv"]) == 0
    rows = capsys.readouterr().out.strip().splitlines()[1:]
    assert len(rows) == 32
    assert all(",ok,5,0," in row for row in rows)  # every cell scored, none diverged


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["run", "--estimator", "ekff"],
            "unknown estimator 'ekff'; valid estimators: autonomous_kkl, curriculum_kkl, dynamic_hyperkkl, ekf, injection_kkl, static_hyperkkl, ukf (did you mean 'ekf'?)",
        ),
        (
            ["run", "--estimator", "ekf", "--system", "duffin"],
            "unknown system 'duffin'; valid systems: duffing, lorenz, rossler, vdp",
        ),
        (
            ["run", "--estimator", "ekf", "--regime", "ramp"],
            "unknown regime 'ramp'; valid regimes: constant, sinusoid, square, zero",
        ),
        (
            ["run", "--estimator", "ekf", "--profile", "huge"],
            "unknown profile 'huge'; valid profiles: quick, standard, paper",
        ),
        (["check", "nope"], "unknown estimator 'nope'"),
    ],
)
def test_bad_names_are_clear_errors(args, message, capsys, tmp_path):
    assert main([*args, *(["--results", str(tmp_path)] if args[0] == "run" else [])]) == 2
    assert message in capsys.readouterr().err


def test_leaderboard_without_results_says_what_to_do(tmp_path, capsys):
    assert main(["leaderboard", "--results", str(tmp_path)]) == 2
    assert "no results under" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["run", "--estimator", "ekf", "--seed", "-3"],
            "seed must be a non-negative integer, got '-3'",
        ),
        (
            ["run", "--estimator", "ekf", "--seed", "x"],
            "seed must be a non-negative integer, got 'x'",
        ),
        (["leaderboard", "--format", "html"], "invalid choice: 'html'"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
    ],
)
def test_bad_arguments_exit_with_usage(args, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_check_command_passes_for_a_builtin(capsys):
    assert main(["check", "ekf"]) == 0
    out = capsys.readouterr().out
    assert "PASS check_causal" in out and "FAIL" not in out
