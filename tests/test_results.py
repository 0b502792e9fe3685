"""Per-cell records: atomic round trip with inf, loading into pandas."""

import math

import pytest

from kkl_bench.results import (
    CellResult,
    cell_path,
    load_results,
    read_cell,
    trajectory_table,
    write_cell,
)


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
    long = trajectory_table(load_results(tmp_path))
    assert len(long) == 4 and set(long["trajectory"]) == {0, 1}


def test_empty_directory_gives_an_empty_table(tmp_path):
    assert load_results(tmp_path).empty
