"""The command line: smoke runs, the leaderboard, and clear errors on bad input."""

import argparse
import importlib
import io
import json
import subprocess
import sys
import warnings
from importlib.metadata import version

import numpy as np
import pandas as pd
import pytest
from tqdm import tqdm

from kkl_bench.cli import COMMANDS, main, recorded_command
from kkl_bench.cli.run import BAR, advance
from kkl_bench.estimator import Estimator
from kkl_bench.registry import estimators
from kkl_bench.support.provenance import provenance
from kkl_bench.testing import check_estimator


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
    assert "| Estimator   | Seeds   | Van der Pol Zero   | Van der Pol Sqr   |" in table
    caption, board, details = table.split("\n\n")
    assert caption.startswith("Track `paper`, profile `quick` (a smoke test: its numbers say")
    assert "`RMSE ± std (SMAPE %)`" in caption and "1 % margin" in caption
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
    assert all(",ok,1,5,0," in row for row in rows)  # every cell scored once, none diverged


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["run", "--estimator", "ekff"],
            "unknown estimator 'ekff'; valid estimators: autonomous_kkl, curriculum_kkl, dynamic_hyperkkl, ekf, enkf, gru_observer, injection_kkl, kalmannet, particle_filter, ring_observer, static_hyperkkl, ukf (did you mean 'ekf'?)",
        ),
        (
            ["run", "--estimator", "static_hyperkkl[gaurd=True]"],
            "static_hyperkkl has no hyperparameter 'gaurd'; valid: pde_weight, injection_hidden, guard",
        ),
        (
            ["run", "--estimator", "static_hyperkkl[guard=yes]"],
            "value 'yes' of 'guard' in 'static_hyperkkl[guard=yes]' is not a Python literal",
        ),
        (
            ["run", "--estimator", "static_hyperkkl[guard]"],
            "malformed parameter 'guard' in 'static_hyperkkl[guard]'; expected key=value",
        ),
        (
            ["run", "--estimator", "ekf", "--system", "duffin"],
            "unknown system 'duffin'; valid systems: chua, duffing, fitzhugh_nagumo, lorenz, lorenz96-n5",
        ),
        (
            ["run", "--estimator", "ekf", "--regime", "ramp"],
            "unknown regime 'ramp' for track(s) paper; valid regimes: constant, sinusoid, square, zero",
        ),
        (
            ["run", "--estimator", "ekf", "--profile", "huge"],
            "unknown profile 'huge'; valid profiles: quick, standard, paper",
        ),
        (["check", "nope"], "unknown estimator 'nope'"),
        (
            ["run", "--estimator", "ekf", "--track", "noisy"],
            "unknown track 'noisy'; valid tracks: paper, far-init, hard, mismatch, more-systems, noise, ood-inputs",
        ),
    ],
)
def test_bad_names_are_clear_errors(args, message, capsys, tmp_path):
    assert main([*args, *(["--results", str(tmp_path)] if args[0] == "run" else [])]) == 2
    assert message in capsys.readouterr().err


def test_leaderboard_without_results_says_what_to_do(tmp_path, capsys, monkeypatch):
    assert main(["leaderboard", "--results", str(tmp_path)]) == 2
    assert "no results under" in capsys.readouterr().err

    monkeypatch.chdir(tmp_path)  # in a checkout, it points to the published board's cells
    (tmp_path / "leaderboard" / "results").mkdir(parents=True)
    assert main(["leaderboard"]) == 2
    assert "the published board's are in leaderboard/results/ (--results leaderboard/results)" in (
        capsys.readouterr().err
    )


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


def test_check_command_passes_for_a_builtin_on_a_two_and_a_three_state_system(capsys):
    assert main(["check", "ekf"]) == 0
    out = capsys.readouterr().out
    assert "PASS duffing check_causal" in out and "PASS lorenz check_causal" in out
    assert "FAIL" not in out and out.endswith("20 passed, 0 failed\n")


class TwoStatesOnly(Estimator):
    """Estimates the x0 box centre, but refuses systems with more than two states."""

    def fit(self, context):
        if context.system.n_x > 2:
            raise NotImplementedError(f"only 2 states, got {context.system.n_x}")
        return super().fit(context)

    def estimate(self, t, y, u):
        context = self.check_fitted()
        centre = (context.x0_low + context.x0_high) / 2
        return np.broadcast_to(centre, (len(y), len(t), 2)).copy()


def test_check_fails_a_plugin_that_raises_on_three_state_systems_and_says_why(capsys):
    estimators.register("two_states_only")(TwoStatesOnly)
    try:
        assert main(["check", "two_states_only"]) == 1
        assert main(["check", "two_states_only", "--system", "vdp"]) == 0
    finally:
        del estimators._loaded["two_states_only"]
    out = capsys.readouterr().out
    assert "PASS duffing check_causal" in out
    assert "FAIL lorenz check_causal: NotImplementedError: only 2 states, got 3" in out
    with pytest.raises(AssertionError, match="lorenz: check_causal: NotImplementedError"):
        check_estimator(TwoStatesOnly())


def test_several_seeds_fit_learned_rows_per_seed_and_filters_once(tmp_path, capsys):
    from kkl_bench.run.harness import RunSpec, plan
    from kkl_bench.suite.task import get_profile

    spec = RunSpec(
        ("ekf", "injection_kkl[adapt=False]", "autonomous_kkl"),
        ("vdp",),
        ("zero",),
        get_profile("quick"),
        seeds=(2, 0, 2),
        results_dir=tmp_path,
    )
    assert spec.seeds == (2, 0) and spec.seeds_for("ekf") == (2,)
    jobs, _ = plan(spec)
    assert [(job.estimator, job.seed) for job in jobs] == [
        ("ekf", 2),
        ("injection_kkl[adapt=False]", 2),
        ("injection_kkl[adapt=False]", 0),
        ("autonomous_kkl", 2),
        ("autonomous_kkl", 0),
    ]
    args = ["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero"]
    assert main([*args, "--seed", "0", "1", "--results", str(tmp_path)]) == 0
    assert "1 cells scored" in capsys.readouterr().out
    assert [
        p.name for p in (tmp_path / "quick" / "ekf" / "vdp").iterdir() if p.suffix == ".json"
    ] == ["zero-seed0.json"]


def test_variant_names_are_canonical_and_stored_under_their_own_name(tmp_path, capsys):
    from kkl_bench.run.results import load_results

    args = ["run", "--system", "vdp", "--regime", "zero", "--results", str(tmp_path)]
    assert main([*args, "--estimator", "ukf", "ukf[ kappa = 1.0, alpha=0.3 ]"]) == 0
    assert "2 cells scored" in capsys.readouterr().out
    assert main([*args, "--estimator", "ukf[alpha=0.3,kappa=1.0]"]) == 0  # same variant: done
    assert "0 cells scored, 1 already done" in capsys.readouterr().out
    results = load_results(tmp_path).set_index("estimator")
    assert sorted(results.index) == ["ukf", "ukf[alpha=0.3,kappa=1.0]"]
    assert results.loc["ukf[alpha=0.3,kappa=1.0]", "estimator_params"] == {
        "alpha": 0.3,
        "beta": 2.0,
        "kappa": 1.0,
        "inflation": None,
        "robust": "auto",
        "threshold": None,
        "quantizer": "auto",
        "engine": "reference",
    }
    assert main(["check", "ukf[alpha=0.3]", "--system", "vdp"]) == 0
    assert "FAIL" not in capsys.readouterr().out


def test_list_shows_the_tracks(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for track in ("paper@v1", "ood-inputs@v1", "noise@v1", "far-init@v1"):
        assert f"track {track} (" in out
    assert "chirp, multisine, random-steps, sinusoid-2x, ramp" in out


def test_leaderboard_of_a_track_not_run_says_how_to_run_it(tmp_path, capsys):
    args = ["--results", str(tmp_path)]
    assert main(["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero", *args]) == 0
    assert main(["leaderboard", "--track", "far-init", *args]) == 2
    assert (
        "no results for track 'far-init'; the results hold paper (run with --track far-init)"
        in (capsys.readouterr().err)
    )
    assert (
        main(
            [
                "run",
                "--estimator",
                "ekf",
                "--system",
                "vdp",
                "--track",
                "far-init",
                "--regime",
                "zero",
                *args,
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["leaderboard", "--track", "far-init", *args]) == 0
    assert "| Van der Pol Zero | settle (s) |" in capsys.readouterr().out.replace("  ", "")
    assert main(["leaderboard", "--track", "summary", *args]) == 0
    assert "| ekf" in capsys.readouterr().out


def test_all_beside_variants_stands_for_every_registered_estimator():
    from kkl_bench.cli.common import names
    from kkl_bench.registry import estimators

    expanded = names(estimators, ["all", "static_hyperkkl[guard=True]"])
    assert expanded == (*estimators.names(), "static_hyperkkl[guard=True]")
    assert names(estimators, ["all"]) == names(estimators, None) == tuple(estimators.names())


def test_list_names_a_broken_plugin_once_with_its_import_error(monkeypatch, capsys):
    reason = "their_package:Thing: ModuleNotFoundError: No module named 'lib'"
    monkeypatch.setattr(estimators, "broken", lambda: {"my_plugin": reason})
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert out.count("my_plugin") == 1 and out.count("No module named") == 1
    assert f"BROKEN estimator my_plugin (not usable): {reason}" in out


def test_scaling_render_only_writes_the_study_without_timing(tmp_path, capsys):
    results, out = str(tmp_path / "results"), tmp_path / "board"
    sizes = ["--system", "lorenz96-n5", "lorenz96-n10", "--regime", "sinusoid"]
    run = ["run", "--estimator", "ekf", "--track", "more-systems", *sizes, "--profile", "quick"]
    assert main([*run, "--results", results]) == 0
    assert main(["scaling", "--results", results, "--out", str(out), "--render-only"]) == 0
    assert "| ekf         | 5   |" in (out / "scaling.md").read_text()
    assert pd.read_csv(out / "scaling.csv")["us_per_step_batch20"].isna().all()  # none timed
    with pytest.raises(SystemExit):  # argparse: not allowed together
        main(["scaling", "--missing-only", "--render-only", "--results", results])
    assert "not allowed with argument --missing-only" in capsys.readouterr().err


def test_compare_help_prints_its_percentages_once(capsys):
    with pytest.raises(SystemExit):
        main(["compare", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "its 90 % interval" in text and "at 5 %." in text and "%%" not in text


def test_a_bad_variant_value_is_an_error_before_any_work(tmp_path, capsys):
    arguments = ["run", "--estimator", "ekf", "enkf[n=-3]", "--results", str(tmp_path)]
    assert main(arguments) == 2
    captured = capsys.readouterr()
    assert "enkf: n=-3 must be an integer of at least 2" in captured.err
    assert "kkl-bench:" not in captured.out and not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("arguments", "suggestion"),
    [
        (["--estimator", "ekff"], "'ekf'"),
        (["--estimator", "ekf", "--system", "duffng"], "'duffing'"),
        (["--estimator", "ekf", "--regime", "sqare"], "'square'"),
        (["--estimator", "ekf", "--track", "hrad"], "'hard'"),
        (["--estimator", "ekf", "--profile", "quik"], "'quick'"),
        (["--estimator", "ekf[inflaton=1.1]"], "'inflation'"),
    ],
)
def test_every_unknown_name_gets_a_suggestion(arguments, suggestion, tmp_path, capsys):
    assert main(["run", *arguments, "--results", str(tmp_path)]) == 2
    assert f"(did you mean {suggestion}?)" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any work


def test_recorded_command_names_no_absolute_path(tmp_path):
    inside, outside = tmp_path / "repo", tmp_path / "scratch" / "refit-results"
    argv = ["run", "--results", str(inside / "leaderboard" / "results"), f"--cache={outside}"]
    recorded = recorded_command([*argv, "--estimator", "ekf"], cwd=inside)
    assert recorded == (
        "kkl-bench run --results leaderboard/results '--cache=<...>/refit-results' --estimator ekf"
    )
    assert recorded_command(["run", "--results", str(inside)], cwd=inside) == (
        "kkl-bench run --results ."
    )


def test_a_run_records_its_results_folder_relative_to_where_it_ran(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero"]
    assert main([*args, "--results", str(tmp_path / "results")]) == 0
    (cell,) = (tmp_path / "results").rglob("*.json")
    command = json.loads(cell.read_text())["provenance"]["command"]
    assert command == f"kkl-bench {' '.join(args)} --results results"


def test_a_system_on_no_track_is_refused_with_the_track_file_to_write(capsys, monkeypatch):
    from kkl_bench.run import spec

    monkeypatch.setattr(spec, "tracks_of", lambda system: [])  # as a new plugin system
    assert main(["run", "--estimator", "ekf", "--system", "chua"]) == 2
    error = capsys.readouterr().err
    assert "chua is on no track: a track file says which tasks a system runs" in error
    assert 'systems = ["chua"]' in error and 'family = "square"' in error
    assert "KKL_BENCH_TRACKS=tracks kkl-bench run ... --system chua --track chua" in error


def test_a_system_on_another_track_is_pointed_to_it(capsys):
    assert main(["run", "--estimator", "ekf", "--system", "chua"]) == 2
    assert "chua is on track(s) more-systems: pass --track more-systems" in capsys.readouterr().err


def test_the_progress_bar_stops_at_its_total_when_the_shares_sum_above_it():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # tqdm warns when it clamps a share above 100 %
        with tqdm(total=0.3, file=io.StringIO(), bar_format=BAR, mininterval=0) as bar:
            for share in (0.1, 0.2):  # 0.1 + 0.2 > 0.3 in floating point
                advance(bar, share)
            assert bar.n == bar.total


def test_version_prints_what_a_cell_records_and_exits(capsys):
    with pytest.raises(SystemExit) as exit_status:
        main(["--version"])
    assert exit_status.value.code == 0
    first, packages = capsys.readouterr().out.strip().splitlines()
    recorded = provenance()
    commit = recorded["git_commit"] or "not a git checkout"
    assert first == f"kkl-bench {version('kkl-bench')} (git {commit})"
    assert f"torch {version('torch')}" in packages and f"Python {recorded['python']}" in packages


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_listed_command_is_declared_with_a_handler_by_its_module(name):
    module, _ = COMMANDS[name]
    siblings = [other for other, (owner, _) in COMMANDS.items() if owner == module]
    parsers = {other: argparse.ArgumentParser(prog=other) for other in siblings}
    importlib.import_module(f"kkl_bench.cli.{module}").add_arguments(parsers)
    assert callable(parsers[name].get_default("handler"))


QUICK_TO_ANSWER = sorted(set(COMMANDS) - {"verify"})
"""The commands whose ``--help`` loads none of the numerical stack: every one but ``verify``,
whose help states its tolerance and file from the verification module (about 1 s)."""


def test_help_and_a_mistyped_command_answer_without_loading_the_numerical_stack():
    """Only the module of the command given is imported: listing the commands, or
    refusing an unknown one, loads none of the heavy packages the commands need; nor does
    a command's ``--help`` or a run with a bad argument (each handler imports what it runs)."""
    helps = [[name, "--help"] for name in QUICK_TO_ANSWER]
    probe = (
        "import contextlib, io, sys\n"
        "from kkl_bench.cli import main\n"
        f"for argv in (['--help'], ['frobnicate'], ['run', '--jobs', '0'], *{helps!r}):\n"
        "    with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()),"
        " contextlib.redirect_stderr(io.StringIO()):\n"
        "        main(argv)\n"
        "print(sorted({'torch', 'pandas', 'numba', 'scipy'} & set(sys.modules)))\n"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True
    ).stdout
    assert loaded.strip() == "[]"


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly(tmp_path):
    """``kkl-bench ... | head``: the reader gone is no error to report; the command stops
    with SIGPIPE's status, as other Unix tools do."""
    command = [sys.executable, "-m", "kkl_bench.cli", "cache", "info", "--cache", str(tmp_path)]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # before the command has written anything
    stderr = process.stderr.read().decode()
    assert process.wait() == 141
    assert stderr == ""
