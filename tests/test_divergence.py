"""Divergence, defined once (protocol section 5): a non-finite estimate or an error beyond the
bound; an estimate that is never finite is an estimator fault."""

import math

import numpy as np

from kkl_bench.analysis.summary import summary_table
from kkl_bench.cli import main
from kkl_bench.estimator import Estimator
from kkl_bench.protocol.metrics import DIVERGENCE_NRMSE, mark_diverged
from kkl_bench.run.results import load_results
from kkl_bench.testing import run_checks
from tests.repository import PROTOCOL


class AllNaN(Estimator):
    family = "model-based"

    def estimate(self, t, y, u):
        return np.full((*y.shape[:2], self.check_fitted().system.n_x), np.nan)


class DivergedTraining(AllNaN):
    """Never finite, after a training whose validation curve ran away (protocol 6.5)."""

    family = "learned"

    def fit_report(self):
        return {
            "spent": {"training": {"steps": 400, "seconds": 1.0}},
            "training_log": {"validation_curve": [[0, 11.9], [200, math.inf], [400, math.nan]]},
        }


class Astronomical(Estimator):
    """Finite, but 1e30 away from every state on its last trajectory."""

    family = "learned"

    def estimate(self, t, y, u):
        x_hat = np.zeros((*y.shape[:2], self.check_fitted().system.n_x))
        x_hat[-1] = 1e30
        return x_hat


def test_a_trajectory_beyond_the_bound_scores_inf_on_every_metric():
    metrics = {
        "rmse": [0.1, 5.0, math.inf],
        "smape": [10.0, 90.0, math.inf],
        "nrmse": [0.5, DIVERGENCE_NRMSE * 1.01, math.inf],
        "per_state_rmse": [[0.1, 0.1], [5.0, 5.0], [math.inf, math.inf]],
        "settling_time_s": [1.0, math.inf, math.inf],
        "estimate_us_per_step": 3.0,
    }
    marked = mark_diverged(metrics)
    assert marked["rmse"] == [0.1, math.inf, math.inf]
    assert marked["smape"] == [10.0, math.inf, math.inf]
    assert marked["per_state_rmse"][1] == [math.inf, math.inf]
    assert marked["estimate_us_per_step"] == 3.0
    at_bound = {**metrics, "nrmse": [0.5, DIVERGENCE_NRMSE, 1.0]}
    assert mark_diverged(at_bound)["rmse"] == [0.1, 5.0, math.inf]  # the bound itself is in


def test_an_astronomical_estimate_is_diverged_and_left_out_of_the_mean(
    register_estimator, tmp_path, capsys
):
    register_estimator("astronomical", Astronomical)
    args = ["run", "--estimator", "astronomical", "--system", "duffing", "--regime", "zero"]
    assert main([*args, "--results", str(tmp_path)]) == 0
    row = summary_table(load_results(tmp_path)).iloc[0]
    assert row["n_diverged"] == 1 and row["rmse_mean"] == math.inf
    assert np.isfinite(row["rmse_median"])  # the others still say how good they are


def test_an_estimate_that_is_never_finite_is_an_error_cell_and_exit_1(
    register_estimator, tmp_path, capsys
):
    register_estimator("all_nan", AllNaN)
    args = ["run", "--estimator", "all_nan", "--system", "duffing", "--regime", "zero"]
    assert main([*args, "--results", str(tmp_path)]) == 1
    cell = load_results(tmp_path).iloc[0]
    assert cell["status"] == "error"
    assert "NaN or inf from the first sample on every trajectory" in cell["error"]


def test_a_never_finite_estimate_after_a_diverged_training_is_a_diverged_cell(
    register_estimator, tmp_path, capsys
):
    register_estimator("diverged_training", DivergedTraining)
    args = ["run", "--estimator", "diverged_training", "--system", "duffing", "--regime", "zero"]
    assert main([*args, "--results", str(tmp_path)]) == 0
    row = summary_table(load_results(tmp_path)).iloc[0]
    assert row["n_diverged"] == row["n_test"] > 0 and row["rmse_mean"] == math.inf
    assert row["converged"] == "diverged"


def test_check_names_the_one_true_failure_of_an_all_nan_estimator():
    failed = [name for _, name, error in run_checks(AllNaN(), "duffing") if error is not None]
    assert failed == ["check_output_shape_and_finite"]


def test_the_protocol_states_the_bound_the_code_applies():
    protocol = PROTOCOL.read_text()
    assert f"NRMSE exceeds {DIVERGENCE_NRMSE:g}" in protocol
