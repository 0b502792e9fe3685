"""``kkl-bench verify``: a cell it has just written is re-derived identical; a changed number
is found, measured and (if asked) replaced; the verdicts reach the board's sentence."""

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from kkl_bench.cli import main
from kkl_bench.run import verification
from kkl_bench.run.results import read_cell
from kkl_bench.run.verification import (
    DRIFTED,
    IDENTICAL,
    VERIFICATION_FILE,
    WITHIN,
    cause_of,
    largest_relative_difference,
    read_verifications,
    recompute,
    verification_sentence,
)

CELL = "ekf/vdp/square-seed0"


@pytest.mark.parametrize(
    ("published", "recomputed", "expected"),
    [
        ([1.0, 2.0], [1.0, 2.0], 0.0),
        ([1.0, 2.0], [1.0, 2.001], 0.0005),  # |2.001 - 2| / 2
        ([1.0, math.inf], [1.5, math.inf], 0.5),  # diverged on both: no difference
        ([1.0, math.nan], [1.0, math.inf], 0.0),  # non-finite on both
        ([1.0, 2.0], [1.0, math.inf], math.inf),  # diverged on one only
        ([1.0, 2.0], [1.0], math.inf),  # another number of trajectories
        ([0.0], [1e-9], math.inf),
    ],
)
def test_the_largest_relative_difference_per_trajectory(published, recomputed, expected):
    assert largest_relative_difference(published, recomputed) == pytest.approx(expected)


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """Results holding two quick cells, written by `kkl-bench run`."""
    folder = tmp_path_factory.mktemp("published") / "results"
    assert main(["run", "--estimator", "ekf", "--system", "vdp", "--regime", "square", "zero",
                 "--results", str(folder)]) == 0  # fmt: skip
    return folder


@pytest.fixture
def results(published, tmp_path):
    """A copy of ``published`` for one test to verify (and change)."""
    return Path(shutil.copytree(published, tmp_path / "results"))


def verify(results, *arguments):
    out = results.parent / "board"
    status = main(["verify", *arguments, "--results", str(results), "--profile", "quick",
                   "--out", str(out)])  # fmt: skip
    return status, read_verifications(out / VERIFICATION_FILE)


def test_a_cell_just_written_is_verified_identical(results, capsys):
    status, verdicts = verify(results, CELL)
    assert status == 0
    assert verdicts[["cell", "verdict", "largest_relative_difference"]].values.tolist() == [
        [f"{CELL}.json", IDENTICAL, 0.0]
    ]
    assert "1 identical, 0 within tolerance, 0 drifted" in capsys.readouterr().out


def test_a_changed_number_is_drifted_with_its_difference_and_replaced_if_asked(results):
    path = results / "quick" / f"{CELL}.json"
    record = json.loads(path.read_text())
    true_rmse = list(record["rmse"])
    record["rmse"][3] *= 1.05  # one trajectory's published RMSE 5 % off
    path.write_text(json.dumps(record))

    status, verdicts = verify(results, CELL, "--tolerance", "0.1")
    assert status == 0 and verdicts["verdict"].tolist() == [WITHIN]

    status, verdicts = verify(results, CELL)
    assert status == 1
    latest = verdicts.iloc[-1]
    assert latest["verdict"] == DRIFTED and not latest["replaced"]
    assert latest["largest_relative_difference"] == pytest.approx(0.05 / 1.05)
    assert read_cell(path).rmse[3] == pytest.approx(true_rmse[3] * 1.05)  # reported only

    status, verdicts = verify(results, CELL, "--replace-drifted")
    assert status == 1 and verdicts.iloc[-1]["replaced"]
    assert np.array_equal(read_cell(path).rmse, true_rmse)
    assert len(verdicts) == 3  # every run's verdicts kept


def test_a_sample_is_verified_in_parallel_and_the_board_says_what_it_found(results, capsys):
    status, verdicts = verify(results, "--sample", "5", "--sample-seed", "7", "--jobs", "2")
    assert status == 0
    assert verdicts["selection"].tolist() == ["random 2 of 2 (--sample-seed 7)"] * 2
    assert sorted(verdicts["cell"]) == [f"{CELL}.json", "ekf/vdp/zero-seed0.json"]
    sentence = verification_sentence(verdicts)
    assert "of the cells it chose (random 2 of 2 (--sample-seed 7)), 2 re-derived from an " in (
        sentence
    )
    assert "2 identical, 0 within a relative 0.0001 of every trajectory's RMSE, 0 drifted." in (
        sentence
    )
    assert verification_sentence(None).startswith("Not verified yet")

    board = results.parent / "board"  # where the verdicts went: the board reads them
    assert main(["publish", "--results", str(results), "--out", str(board)]) == 0
    reproduce = (board / "README.md").read_text().split("## Reproduce")[1]
    assert sentence in reproduce and f"| `{CELL}.json` | identical " in reproduce


def test_cells_that_need_one_model_not_trained_yet_are_not_recomputed_at_once(
    results, capsys, monkeypatch
):
    given, execute = [], verification.execute

    def recording(function, arguments, jobs, claims=None):
        given.append(claims)
        return execute(function, arguments, jobs, claims=claims)

    monkeypatch.setattr(verification, "execute", recording)
    monkeypatch.setattr(verification, "trained_models", lambda cell: {(cell.system, "model")})
    assert verify(results, "--sample", "5", "--jobs", "2")[0] == 0
    assert given == [[{("vdp", "model")}] * 2]


def test_an_interrupted_run_goes_on_where_it_stopped(results, capsys):
    sample = ["--sample", "5", "--sample-seed", "7"]
    verify(results, *sample)
    verdicts_file = results.parent / "board" / VERIFICATION_FILE
    lines = verdicts_file.read_text().splitlines(keepends=True)
    verdicts_file.write_text("".join(lines[:-1]))  # cut after its first verdict
    first = read_verifications(verdicts_file)
    capsys.readouterr()

    status, verdicts = verify(results, *sample, "--resume")
    assert status == 0
    assert "1 cell(s) verified before" in capsys.readouterr().err
    assert len(verdicts) == 2 and verdicts["run"].nunique() == 1  # one run, each cell once
    assert verdicts.iloc[0].equals(first.iloc[0])  # the verdict before was not recomputed
    assert sorted(verdicts["cell"]) == [f"{CELL}.json", "ekf/vdp/zero-seed0.json"]


def test_a_drift_is_blamed_on_the_budget_only_when_the_steps_or_samples_differ(results):
    published = read_cell(results / "quick" / f"{CELL}.json")
    spent = {"phase2": {"steps": 4000, "samples": 10, "seconds": 1.0, "git_commit": "a"}}

    def made(steps, seconds, **report):
        phase = {**spent["phase2"], "steps": steps, "seconds": seconds}
        return dataclasses.replace(published, fit_report={"spent": {"phase2": phase}, **report})

    assert cause_of(made(4000, 1.0), made(8000, 1.0)).startswith("another training budget")
    assert cause_of(made(4000, 1.0), made(4000, 9.0)) == ""  # another training's seconds
    assert (
        cause_of(made(4000, 1.0, gain=1), made(4000, 9.0, gain=2)) == "fit report differs in gain"
    )


def test_the_estimate_counts_a_shared_model_once_and_each_filter_fit(results, capsys):
    """Two cells of KKL rows on one Phase-1 model (its 100 s counted at the first only),
    their own phases (30 s and 20 s), and a filter's cell whose 2 s fit caches nothing
    (counted at each cell); each scored at 50 µs a step, 5 trajectories of 1001 samples."""
    published = read_cell(results / "quick" / f"{CELL}.json")
    phase1 = {"steps": 10, "seconds": 100.0}

    def cell(estimator, own=None, fit_time_s=2.0):
        spent = {} if own is None else {"phase1": phase1, "phase2": {"steps": 5, "seconds": own}}
        return dataclasses.replace(
            published,
            estimator=estimator,
            fit_report={"spent": spent},
            fit_time_s=fit_time_s,
            estimate_us_per_step=50.0,
            n_test=5,
        )

    scoring = 50e-6 * 5 * 1001  # the paper track's 20 s at dt = 0.02: 1001 samples
    cells = [
        cell("static_hyperkkl", 30.0),
        cell("dynamic_hyperkkl", 20.0),
        cell("ekf"),
        cell("ekf"),
    ]
    assert verification.estimated_seconds(cells) == pytest.approx(
        [130.0 + scoring, 20.0 + scoring, 2.0 + scoring, 2.0 + scoring]
    )

    assert verify(results, CELL)[0] == 0
    assert "estimated " in capsys.readouterr().err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ([CELL, "--resume"], "--resume: no verification run in"),
        ([], "name the cells to verify or give --sample N"),
        (["ekf/vdp/sqare-seed0"], "did you mean 'ekf/vdp/square-seed0'?"),
        ([CELL, "--tolerance", "-1"], "--tolerance must be a non-negative number"),
    ],
)
def test_bad_verify_arguments_are_named(results, capsys, arguments, message):
    assert verify(results, *arguments)[0] == 2
    assert message in capsys.readouterr().err


def test_only_the_cells_own_row_is_refitted(tmp_path, capsys):
    """A mismatch cell of a filter that also has a ``+logged`` row: verifying the filter's
    cell fits the filter alone (a run of it fits both)."""
    results = tmp_path / "results"
    arguments = ["--system", "vdp", "--track", "mismatch", "--regime", "params25-sinusoid"]
    assert main(["run", "--estimator", "ekf", *arguments, "--results", str(results)]) == 0
    assert {p.name for p in (results / "quick").iterdir()} == {"ekf", "ekf+logged"}
    published = read_cell(
        results / "quick" / "ekf" / "vdp" / "mismatch" / "params25-sinusoid-seed0.json"
    )
    recomputed, _ = recompute(published, tmp_path / "work")
    assert recomputed.rmse == published.rmse
    assert {p.name for p in (tmp_path / "work" / "results" / "quick").iterdir()} == {"ekf"}
