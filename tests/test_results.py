"""Per-cell records: atomic round trip with inf, loading into pandas."""

import json
import math
import os

import numpy as np
import pytest

from kkl_bench.run.results import (
    CellResult,
    KeptEstimate,
    cell_path,
    estimate_path,
    load_results,
    read_cell,
    read_estimate,
    write_cell,
)
from kkl_bench.support import provenance as provenance_module
from tests.git_repo import commit_all


def make_cell(**overrides):
    fields = dict(
        estimator="ekf",
        system="duffing",
        regime="zero",
        task="duffing/zero@v1",
        profile="quick",
        seed=0,
        status="ok",
        n_test=2,
        rmse=[0.1, math.inf],
        smape=[5.0, math.inf],
        nrmse=[0.2, math.inf],
        per_state_rmse=[[0.1, 0.1], [math.inf, math.inf]],
        fit_time_s=0.0,
        estimate_us_per_step=12.5,
    )
    return CellResult(**{**fields, **overrides})


def test_round_trip_keeps_inf_and_leaves_no_temporary_file(tmp_path):
    path = write_cell(tmp_path, make_cell())
    assert path == cell_path(tmp_path, "ekf", "duffing", "zero", "quick", 0)
    assert read_cell(path) == make_cell()
    assert [p.name for p in path.parent.iterdir()] == ["zero-seed0.json"]
    assert read_cell(path).n_diverged == 1


def test_load_results_adds_summary_columns(tmp_path):
    write_cell(tmp_path, make_cell())
    write_cell(
        tmp_path, make_cell(regime="constant", rmse=[0.1, 0.3], smape=[1.0, 3.0], nrmse=[1.0, 1.0])
    )
    table = load_results(tmp_path).set_index("regime")
    assert table.loc["zero", "rmse_mean"] == math.inf
    assert table.loc["constant", "rmse_mean"] == pytest.approx(0.2)
    assert table.loc["constant", "rmse_std"] == pytest.approx(0.1)


def test_empty_directory_gives_an_empty_table(tmp_path):
    assert load_results(tmp_path).empty


def test_records_and_kept_estimates_follow_the_umask(tmp_path):
    t = np.arange(3) * 0.05
    kept = KeptEstimate(t=t, x=np.ones((3, 2)), x_hat=np.zeros((3, 2)))
    path = write_cell(tmp_path, make_cell(), kept)
    mask = os.umask(0)
    os.umask(mask)
    for written in (path, estimate_path(path)):
        assert written.stat().st_mode & 0o777 == 0o666 & ~mask
    loaded = read_estimate(path)
    np.testing.assert_array_equal(loaded.x_hat, kept.x_hat)
    write_cell(tmp_path, make_cell())  # rescored without an estimate: no stale file is left
    assert read_estimate(path) is None


def test_a_track_cell_lives_in_its_track_folder(tmp_path):
    cell = make_cell(
        track="noise", regime="square-sigma0.1", task="noise/duffing/square-sigma0.1@v1"
    )
    path = write_cell(tmp_path, cell)
    assert path == tmp_path / "quick" / "ekf" / "duffing" / "noise" / "square-sigma0.1-seed0.json"
    write_cell(tmp_path, make_cell())
    table = load_results(tmp_path)
    assert sorted(table["track"]) == ["noise", "paper"]


def test_a_format_1_record_reads_as_a_paper_track_cell(tmp_path):
    path = write_cell(tmp_path, make_cell())
    record = json.loads(path.read_text())
    for key in ("track", "settling_time_s"):
        del record[key]
    record["record_format"] = 1
    path.write_text(json.dumps(record))
    cell = read_cell(path)
    assert (cell.track, cell.settling_time_s, cell.record_format) == ("paper", [], 1)


def test_the_commit_is_dirty_for_changed_code_not_for_changed_results(tmp_path):
    (tmp_path / "leaderboard").mkdir()
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "leaderboard" / "cell.json").write_text("{}\n")
    commit_all(tmp_path, "start")
    clean = provenance_module._git_commit(tmp_path)
    assert clean and not clean.endswith("-dirty")
    (tmp_path / "leaderboard" / "cell.json").write_text('{"rmse": 0.1}\n')  # a run wrote
    assert provenance_module._git_commit(tmp_path) == clean
    (tmp_path / "code.py").write_text("x = 2\n")
    assert provenance_module._git_commit(tmp_path) == clean + "-dirty"
    assert provenance_module._git_commit(tmp_path.parent / "absent") is None
