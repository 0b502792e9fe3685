"""`kkl-bench trainings`: each fit's trainings read once from its cells' reports, and a
row's RMSE against another folder's."""

import math

import numpy as np
import pandas as pd
import pytest

from kkl_bench.analysis import trainings
from kkl_bench.cli import main


def report(
    decoder_steps, stopped="plateau", best=None, level="sine 0.2-0.8 rad/s", halved_at=(4000,)
):
    """A fit report of a Phase-1 decoder and one curriculum level (whose name has dots)."""
    decoder = {
        "validation_curve": [[0, 1.0], [decoder_steps, 0.1]],
        "steps": decoder_steps,
        "stopped": stopped,
        "best_step": decoder_steps if best is None else best,
        "lr_reductions": list(halved_at),
    }
    old_level = {"validation_curve": [[0, 1.0], [200, 0.5], [400, 0.4]]}  # before the rule
    return {
        "phase1_log": {"decoder": decoder},
        "training_log": {level: old_level},
        "spent": {"phase1": {"steps": decoder_steps}},
    }


def cells():
    """Two seeds of one row on Duffing, each fit scored on two regimes; a filter's cell."""
    rows = []
    for seed, fit in ((0, report(12000, best=11800)), (1, report(20000, "cap", best=14000))):
        for regime, rmse in (("zero", 0.1 + seed), ("square", 0.3 + seed)):
            rows.append(("curriculum_kkl", seed, regime, fit, rmse))
    rows.append(("ekf", 0, "zero", {}, 0.05))
    return pd.DataFrame(
        [
            {
                "estimator": row,
                "system": "duffing",
                "task": f"duffing/{regime}@v1",
                "regime": regime,
                "seed": seed,
                "fit_report": fit,
                "rmse_mean": rmse,
                "status": "ok",
            }
            for row, seed, regime, fit, rmse in rows
        ]
    )


def test_each_fit_is_read_once_with_its_trainings_steps_stop_and_kept_step():
    records = trainings.training_records(cells())
    assert len(records) == 4  # two fits of two trainings; the filter trains nothing
    table = trainings.training_table(records).set_index("Training")
    decoder = table.loc["phase1_log.decoder"]
    assert decoder["Fits"] == 2 and decoder["Steps (median)"] == 16000
    assert decoder["Steps (range)"] == "12,000-20,000"
    assert (decoder["Stopped: plateau"], decoder["Stopped: cap"]) == (1, 1)
    assert decoder["Kept step (median)"] == 12900
    level = table.loc["training_log.sine 0.2-0.8 rad/s"]  # before the rule: its last step
    assert level["Stopped: not recorded"] == 2 and level["Steps (median)"] == 400
    assert level["Kept step (median)"] == 400
    assert "Stopped: diverged" not in table.columns  # only the reasons that occurred


def test_a_rows_rmse_is_compared_on_the_cells_both_folders_hold():
    after = cells()
    before = after.assign(rmse_mean=after["rmse_mean"] * 2)
    before = before[~((before["seed"] == 1) & before["task"].str.contains("square"))]
    change = trainings.rmse_change(before, after).set_index("Row")
    row = change.loc["curriculum_kkl"]
    assert row["Cells"] == 3
    assert row["RMSE after"] == pytest.approx((0.1 + 0.3 + 1.1) / 3)
    assert row["after / before"] == pytest.approx(0.5)
    assert math.isclose(change.loc["ekf", "after / before"], 0.5)


def test_the_converged_share_is_counted_per_track_over_learned_cells_only():
    paper = cells().assign(track="paper")  # the plateau on seed 0, the cap on seed 1: `no`
    fit = report(12000, best=11800)
    plateau = {key: fit[key] for key in ("phase1_log", "spent")}  # stopped by the rule only
    hard = paper.assign(track="hard", fit_report=[plateau] * 4 + [{}])
    sentence = trainings.converged_by_track(pd.concat([paper, hard], ignore_index=True))
    assert sentence.endswith(  # tracks in order of name; the filter's cell is not counted
        "by track: `hard` 2 of 2 (100.0%); `paper` 0 of 2 (0.0%; 2 no)."
    )
    filters = paper[paper["estimator"] == "ekf"]
    assert trainings.converged_by_track(filters) == ""


def test_a_rows_rmse_change_by_regime_keeps_the_regimes_apart():
    after = cells().sort_values("regime", kind="stable")  # square's cells first
    before = after.assign(rmse_mean=after["rmse_mean"] * np.where(after["regime"] == "zero", 2, 4))
    change = trainings.rmse_change(before, after, by_regime=True).set_index(["Row", "Regime"])
    assert list(change.index) == [  # the paper's order of regimes, whatever the cells' order
        ("curriculum_kkl", "zero"),
        ("curriculum_kkl", "square"),
        ("ekf", "zero"),
    ]
    zero, square = change.loc[("curriculum_kkl", "zero")], change.loc[("curriculum_kkl", "square")]
    assert (zero["Cells"], square["Cells"]) == (2, 2)
    assert zero["RMSE after"] == pytest.approx((0.1 + 1.1) / 2)
    assert zero["after / before"] == pytest.approx(0.5)
    assert square["after / before"] == pytest.approx(0.25)


def test_a_cell_diverged_in_either_folder_is_left_out_of_both_means_and_counted():
    after = cells()
    before = after.assign(rmse_mean=after["rmse_mean"] * 2)
    before.loc[before["estimator"] == "ekf", "rmse_mean"] = np.inf
    first = after.index[after["estimator"] == "curriculum_kkl"][0]
    after.loc[first, "rmse_mean"] = np.inf  # seed 0 on zero diverged, after only
    unsupported = pd.DataFrame(  # a row that scores nothing in either folder is not compared
        [{"estimator": "ring_observer", "system": "duffing", "task": "duffing/zero@v1",
          "regime": "zero", "seed": 0, "rmse_mean": np.nan, "status": "unsupported"}]
    )  # fmt: skip
    before, after = (pd.concat([folder, unsupported]) for folder in (before, after))
    change = trainings.rmse_change(before, after).set_index("Row")
    assert "ring_observer" not in change.index
    ekf, row = change.loc["ekf"], change.loc["curriculum_kkl"]
    assert (ekf["Cells"], ekf["Diverged"]) == (1, 1)
    assert np.isnan(ekf["RMSE before"]) and np.isnan(ekf["after / before"])  # not after / inf
    assert (row["Cells"], row["Diverged"]) == (4, 1)
    assert row["RMSE after"] == pytest.approx((0.3 + 1.1 + 1.3) / 3)  # seed 0 zero left out
    assert row["after / before"] == pytest.approx(0.5)  # over the same three cells


def test_the_command_prints_a_fitted_rows_trainings_and_its_change(tmp_path, capsys):
    results = str(tmp_path / "results")
    run = ["run", "--system", "vdp", "--regime", "zero", "--results", results]
    assert main([*run, "--estimator", "autonomous_kkl", "ekf"]) == 0
    capsys.readouterr()
    assert main(["trainings", "--results", results, "--before", results]) == 0
    steps, converged, capped, change, _, costs = capsys.readouterr().out.split("\n\n")
    assert "| autonomous_kkl | vdp      | phase1_log.encoder |" in steps
    assert "| autonomous_kkl | vdp      | phase1_log.decoder |" in steps and "ekf" not in steps
    assert "of 1 learned cells" in converged  # the filter's cell is not a learned one
    # the quick profile's caps are small: its trainings end there, and are named
    assert capped.startswith("Reached the cap (") and "`autonomous_kkl` on vdp, seed 0" in capped
    pytest.importorskip("matplotlib")  # and the board names them under its cost table
    board = tmp_path / "board"
    assert main(["publish", "--results", results, "--profile", "quick", "--out", str(board)]) == 0
    assert capped.strip() in (board / "README.md").read_text().replace("\n", " ")
    assert "| ekf " in change and change.count("|                1 |") == 2  # after / before
    assert "| autonomous_kkl | vdp      |             1 |            1 |" in costs
    assert main(["trainings", "--results", results, "--before", results, "--by-regime"]) == 0
    assert "| Row            | System   | Regime   |" in capsys.readouterr().out.split("\n\n")[-3]
    assert main(["trainings", "--results", results, "--by-regime"]) == 2
    assert "--by-regime compares with --before DIR" in capsys.readouterr().err
    filters = str(tmp_path / "filters")
    assert (
        main(
            [
                "run",
                "--system",
                "vdp",
                "--regime",
                "zero",
                "--estimator",
                "ekf",
                "--results",
                filters,
            ]
        )
        == 0
    )
    assert main(["trainings", "--results", filters]) == 2
    assert "no trained fits among the paper track's cells" in capsys.readouterr().err


def test_a_rows_fits_cost_is_compared_per_fit_on_the_clock_each_recorded():
    def cell(row, seed, regime, spent):
        return {
            "estimator": row,
            "system": "duffing",
            "task": f"duffing/{regime}@v1",
            "regime": regime,
            "seed": seed,
            "fit_report": {"spent": spent},
        }

    def cosine(samples, seconds):  # before: wall time only
        return {"phase2": {"steps": 16000, "samples": samples, "seconds": seconds}}

    before = pd.DataFrame(
        [
            cell("gru_observer", seed, regime, cosine(1000 * (2 * seed + 1), 100 * (2 * seed + 1)))
            for seed in (0, 1)
            for regime in ("zero", "square")
        ]
        + [cell("kalmannet", 0, "zero", cosine(10, 1)), cell("ekf", 0, "zero", {})]
    )
    seed0 = {
        "phase1": {"steps": 1000, "samples": 600, "seconds": 90, "processor_seconds": 30},
        "phase2": {"steps": 0, "samples": 0},  # no second phase: left out
    }
    seed1 = {
        "phase1": {"steps": 3000, "samples": 1800, "seconds": 100, "processor_seconds": 90},
        "phase2": {"steps": 10, "samples": 0, "seconds": 1},  # its wall time only
    }
    after = pd.DataFrame(
        [cell("gru_observer", 0, regime, seed0) for regime in ("zero", "square")]
        + [cell("gru_observer", 1, "zero", seed1), cell("ekf", 0, "zero", {})]
    )
    (row,) = trainings.fit_cost_change(before, after).to_dict("records")  # kalmannet: before only
    assert row == {
        "Row": "gru_observer",
        "System": "duffing",
        "Fits before": 2,
        "Fits after": 2,
        "Steps (median) before": 16000,
        "Steps (median) after": 2005,
        "Seconds (median) before": 200.0,
        "Seconds (median) after": 60.5,
        "Samples/s before": 10.0,
        "Samples/s after": pytest.approx(2400 / 121),
        "Clock before": "wall",
        "Clock after": "processor, wall",
    }


def test_a_diverged_training_says_why_and_which_state_was_kept():
    under_rule = {
        "validation_curve": [[0, 1.0], [200, 0.5], [400, math.inf]],
        "stopped": "diverged",
        "best_step": 200,
    }
    assert trainings.divergence(under_rule) == "validation error inf at step 400"
    assert trainings.divergence({**under_rule, "stopped": "cap"}) == ""
    rose = {"validation_curve": [[0, 1.0], [200, 0.1], [400, 0.25]]}  # before the rule
    assert (
        trainings.divergence(rose)
        == "validation error 0.25 at its last step 400, 2.5 times its best"
    )
    assert trainings.divergence({"validation_curve": [[0, 1.0], [200, 0.1], [400, 0.19]]}) == ""
    not_finite = {"validation_curve": [[0, 1.0], [200, math.nan], [400, 0.1]]}
    assert trainings.divergence(not_finite) == "validation error not finite at step 200"

    frame = cells()  # seed 0's zero cell from another fit, whose curriculum level rose
    frame.at[0, "fit_report"] = {**report(400), "training_log": {"level": rose}}
    spent = {"phase1": {"steps": 400}}  # the last cell: a decoder whose error was not finite
    frame.at[4, "fit_report"] = {"phase1_log": {"decoder": under_rule}, "spent": spent}
    sentence = trainings.diverged_sentence(trainings.training_records(frame))
    assert sentence.startswith("Diverged (2 of ")
    assert (
        "`curriculum_kkl` on duffing, seed 0, `training_log.level`: validation error 0.25"
        in sentence
    )
    assert (
        "`ekf` on duffing, seed 0, `phase1_log.decoder`: validation error inf at step 400 (the state of step 200 kept)."
        in sentence
    )
    assert trainings.diverged_sentence(trainings.training_records(cells())) == ""


def test_a_training_at_its_cap_is_named_with_how_far_its_learning_rate_came_down():
    records = trainings.training_records(cells())  # seed 1's decoder reached its cap
    assert records["halvings"].isna().tolist() == [False, True, False, True]  # the level:
    assert records["halvings"].dropna().tolist() == [1, 1]  # from before the rule
    assert trainings.capped_sentence(records) == (
        "Reached the cap (1 of 4 trainings): `curriculum_kkl` on duffing, seed 1, "
        "`phase1_log.decoder`: 20000 steps, its learning rate halved once (the last at step "
        "4000), the state of step 14000 kept."
    )
    frame = cells()
    halved = report(30000, "cap", best=29800, halved_at=(9000, 17400, 21000, 25200, 29600))
    unhalved = report(30000, "cap", best=30000, halved_at=())
    for index, fit in ((0, halved), (1, halved), (2, unhalved), (3, unhalved)):
        frame.at[index, "fit_report"] = fit
    sentence = trainings.capped_sentence(trainings.training_records(frame), "fits' trainings")
    assert sentence.startswith("Reached the cap (2 of 4 fits' trainings): ")
    assert (
        "seed 0, `phase1_log.decoder`: 30000 steps, its learning rate halved 5 times (the last "
        "at step 29600), the state of step 29800 kept; " in sentence
    )
    assert sentence.endswith(
        "seed 1, `phase1_log.decoder`: 30000 steps, its learning rate never halved, the state "
        "of step 30000 kept."
    )
    plateaued = cells().assign(fit_report=[report(12000)] * 4 + [{}])
    assert trainings.capped_sentence(trainings.training_records(plateaued)) == ""


def test_the_board_reads_a_cell_converged_only_when_every_seeds_fit_did():
    frame = cells()  # seed 1's decoder reached its cap: both of the row's cells read no
    verdicts = trainings.cell_verdicts(frame)
    assert verdicts["task"].tolist() == ["duffing/zero@v1", "duffing/square@v1"]  # not ekf's
    assert verdicts["converged"].tolist() == ["no", "no"]
    assert trainings.converged_sentence(verdicts) == (
        "Converged, as the board reads it (per row, system and task, over its seeds' fits): "
        "2 no of 2 learned cells, 0.0% yes (`curriculum_kkl` on duffing, no: 2)."
    )
    plateaued = {"phase1_log": report(12000)["phase1_log"], "spent": {"phase1": {"steps": 1}}}
    decoder = plateaued["phase1_log"]["decoder"]
    diverged = {**plateaued, "phase1_log": {"decoder": {**decoder, "stopped": "diverged"}}}
    learned = frame["estimator"] == "curriculum_kkl"
    frame.loc[learned & (frame["seed"] == 0), "fit_report"] = [plateaued, plateaued]
    frame.loc[
        learned & frame["task"].str.contains("square") & (frame["seed"] == 1), "fit_report"
    ] = [diverged]
    assert trainings.converged_sentence(trainings.cell_verdicts(frame)) == (
        "Converged, as the board reads it (per row, system and task, over its seeds' fits): "
        "1 no, 1 diverged of 2 learned cells, 0.0% yes (`curriculum_kkl` on duffing, no: 1; "
        "`curriculum_kkl` on duffing, diverged: 1)."
    )
    frame = frame[frame["seed"] == 0]  # both cells from seed 0's fit alone
    assert trainings.converged_sentence(trainings.cell_verdicts(frame)) == (
        "Converged, as the board reads it (per row, system and task, over its seeds' fits): "
        "2 yes of 2 learned cells, 100.0% yes."
    )
