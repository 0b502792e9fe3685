"""Estimator families: declared, recorded, listed, and read by every learned-versus-model-based
table (never a row's name or fit time)."""

import numpy as np
import pandas as pd
import pytest

from kkl_bench import families
from kkl_bench.analysis import comparisons
from kkl_bench.cli import main
from kkl_bench.estimator import Estimator
from kkl_bench.registry import estimators


class RobustFilterPlugin(Estimator):
    """A plugin filter that trains nothing and says so."""

    family = "model-based"

    def estimate(self, t, y, u):
        return np.zeros((*y.shape[:2], 2))


class UndeclaredPlugin(Estimator):
    def estimate(self, t, y, u):
        return np.zeros((*y.shape[:2], 2))


def test_every_built_in_estimator_declares_its_family():
    declared = {name: families.declared_family(estimators.get(name)) for name in estimators.names()}
    assert set(declared.values()) <= set(families.FAMILIES)
    assert {name for name, family in declared.items() if family == "model-based"} == {
        "ekf",
        "ukf",
        "enkf",
    }
    assert {name for name, family in declared.items() if family == "limit"} == {"particle_filter"}


@pytest.mark.parametrize(
    ("row", "family"),
    [
        ("ekf[engine='compiled']", "model-based"),
        ("ukf+logged", "model-based"),
        ("particle_filter[n=20000]", "limit"),
        ("particle_filter+truth", "limit"),
        ("particle_filter+logged", "model-based"),  # a calibrated model is no task's truth
        ("kalmannet+logged", "learned"),
        ("static_hyperkkl[guard=True]", "learned"),
        ("not_installed_here", "learned"),
    ],
)
def test_a_row_reads_its_estimators_family(row, family):
    assert families.row_family(row) == family


def test_a_recorded_family_wins_over_the_installed_one():
    assert families.row_family("ekf", recorded="learned") == "learned"


def test_a_family_outside_the_three_is_refused_with_the_valid_ones():
    class Odd(Estimator):
        family = "hybrid"

        def estimate(self, t, y, u):
            return y

    with pytest.raises(ValueError, match=r"family='hybrid'.*model-based, learned, limit"):
        families.estimator_family(Odd)


def test_an_undeclared_plugin_reads_as_learned_and_list_says_it_is_undeclared(
    register_estimator, capsys
):
    register_estimator("robust_plugin", RobustFilterPlugin)
    register_estimator("undeclared_plugin", UndeclaredPlugin)
    assert families.row_family("undeclared_plugin") == "learned"
    assert main(["list"]) == 0
    listed = capsys.readouterr().out
    assert "robust_plugin (model-based)" in listed
    assert "undeclared_plugin (learned, undeclared)" in listed
    assert "ekf (model-based)" in listed and "particle_filter (limit)" in listed


def test_a_model_based_plugin_is_never_counted_as_learned(register_estimator):
    """The plugin beats every row: it is the best model-based row and the comparison's
    model-based side, and the best learned row is the real learned one."""
    register_estimator("robust_plugin", RobustFilterPlugin)
    rng = np.random.default_rng(1)
    base = rng.uniform(0.9, 1.1, size=20)

    def row(estimator, factor):
        rmse = factor * base
        return {
            "estimator": estimator,
            "track": "hard",
            "system": "duffing",
            "regime": "outliers-sinusoid",
            "status": "ok",
            "n_diverged": 0,
            "rmse_mean": float(rmse.mean()),
            "rmse_trajectories": rmse[None, :],
        }

    summary = pd.DataFrame(
        [
            row("particle_filter", 0.9),
            row("robust_plugin", 1.0),
            row("ukf", 3.0),
            row("kalmannet", 1.2),
        ]
    )
    summary["family"] = summary["estimator"].map(families.row_family)
    limit = comparisons.limit_frame(summary).iloc[0]
    assert (limit["best_model_based"], limit["best_learned"]) == ("robust_plugin", "kalmannet")
    versus = comparisons.learned_versus_model_based(summary, "hard").iloc[0]
    assert (versus["a"], versus["b"], versus["verdict"]) == (
        "kalmannet",
        "robust_plugin",
        "b lower",
    )
    answer = comparisons.one_line_answer(summary)
    assert answer.startswith("Lowest RMSE of the 1 cells (the limit aside): `robust_plugin` in 1")
    assert "the best model-based row 1.11 times and the best learned row 1.33 times" in answer


def test_the_headroom_sentence_counts_cells_where_the_best_model_based_row_is_far():
    summary = pd.DataFrame(
        [
            {"estimator": e, "system": "vdp", "regime": r, "status": "ok", "rmse_mean": v}
            for r, pf, ukf in (("sinusoid", 0.1, 0.2), ("square", 0.1, 0.12))
            for e, v in (("particle_filter", pf), ("ukf", ukf))
        ]
    )
    assert comparisons.headroom_sentence(summary) == (
        "The best model-based row is at least 1.3 times the limit in 1 of 2 cells "
        "(median 1.60 times)."
    )
