"""The scaling study's arithmetic: cell summaries, fitted exponents, crossovers, the report."""

import math

import numpy as np
import pandas as pd
import pytest

from kkl_bench import scaling


def cells(estimator, n, rmse, fit_time, status="ok", regimes=("zero", "sinusoid"), report=None):
    return [
        dict(
            estimator=estimator,
            system=f"lorenz96-n{n}",
            regime=regime,
            track="more-systems",
            seed=0,
            task=f"more-systems/lorenz96-n{n}/{regime}@v1",
            protocol="v1+E1",
            status=status,
            error=None if status == "ok" else "Traceback...\nMemoryError: 40 GB",
            rmse=[rmse, rmse],
            smape=[1.0, 1.0],
            nrmse=[0.1, 0.1],
            fit_time_s=fit_time,
            estimate_us_per_step=1.0,
            fit_report=report,
        )
        for regime in regimes
    ]


def test_cell_summary_averages_regimes_and_reports_failures():
    results = pd.DataFrame(
        cells("ekf", 5, 0.1, 0.0)
        + cells("ekf", 10, 0.3, 0.0)
        + cells("big", 5, 0.2, 30.0)
        + cells("big", 10, math.nan, math.nan, status="error")
        + [{**cells("ekf", 5, 9.9, 0.0)[0], "track": "paper", "system": "lorenz"}]
    )
    summary = scaling.cell_summary(results).set_index(["estimator", "n"])
    assert summary.loc[("ekf", 10), "rmse"] == pytest.approx(0.3)
    assert summary.loc[("big", 5), "fit_time_s"] == 30.0
    assert summary.loc[("big", 10), "status"] == "MemoryError: 40 GB"
    assert math.isnan(summary.loc[("big", 10), "rmse"])
    with pytest.raises(ValueError, match="no more-systems cells of lorenz96-n5"):
        scaling.cell_summary(results[results["track"] == "paper"])


def test_fit_time_is_the_training_time_of_every_phase_wherever_it_ran():
    def spent(phase1, phase2):
        return {"spent": {"phase1": phase1, "phase2": phase2}}

    trained = {"steps": 100, "samples": 10, "seconds": 600.0}
    results = pd.DataFrame(
        # Phase 1 loaded from the cache: the fit took 2 s, its trainings 600 + 50 s
        cells("kkl", 5, 0.1, 2.0, report=spent(trained, {**trained, "seconds": 50.0}))
        # nothing of its own to train
        + cells("plain", 5, 0.1, 0.5, report=spent(trained, {"steps": 0, "samples": 0}))
        # a Phase 1 trained before training times were recorded
        + cells("old", 5, 0.1, 9.0, report=spent({"steps": 100, "samples": 10}, trained))
        + cells("ekf", 5, 0.1, 1e-4)  # no training: its wall time
    )
    summary = scaling.cell_summary(results).set_index("estimator")["fit_time_s"]
    assert summary["kkl"] == 650.0
    assert summary["plain"] == 600.0
    assert math.isnan(summary["old"])
    assert summary["ekf"] == 1e-4


def frame():
    """Costs that are exact power laws: ekf flat then n^1; kkl n^2 from a cheap start."""
    n = np.array([5, 10, 20, 40])
    rows = []
    for name, batch20, batch1, fit in (
        ("ekf", 300 * (n / 5.0) ** 0, 400 * (n / 5.0) ** 1, 0 * n + 1e-3),
        ("kkl", 2 * (n / 5.0) ** 2, 50 * (n / 5.0) ** 0.5, 10 * (n / 5.0) ** 3),
    ):
        for i, size in enumerate(n):
            rows.append(
                dict(
                    estimator=name,
                    n=size,
                    status="ok",
                    rmse=0.1,
                    nrmse=0.01,
                    fit_time_s=fit[i],
                    us_per_step_batch20=batch20[i],
                    us_per_step_batch1=batch1[i],
                )
            )
    return pd.DataFrame(rows)


def test_exponents_recover_power_laws():
    fitted = scaling.exponents(frame()).set_index("estimator")
    assert fitted.loc["kkl", "us_per_step_batch20"] == pytest.approx(2.0)
    assert fitted.loc["kkl", "us_per_step_batch1"] == pytest.approx(0.5)
    assert fitted.loc["kkl", "fit_time_s"] == pytest.approx(3.0)
    assert fitted.loc["ekf", "us_per_step_batch20"] == pytest.approx(0.0, abs=1e-12)
    assert fitted.loc["ekf", "us_per_step_batch1"] == pytest.approx(1.0)
    assert math.isnan(fitted.loc["ekf", "fit_time_s"])  # 1 ms at every size: it does not train


def test_crossover_lists_the_sizes_cheaper_than_the_ekf():
    # kkl batch 20: 2 * (n/5)^2 = 2, 8, 32, 128 against 300; batch 1: 50 * (n/5)^0.5 against
    # 400 * n/5; both cheaper everywhere
    costly = frame()
    assert scaling.crossover(costly) == {("kkl", 20): [5, 10, 20, 40], ("kkl", 1): [5, 10, 20, 40]}
    costly.loc[costly["estimator"] == "kkl", "us_per_step_batch20"] *= 50  # 100, 400, 1600, 6400
    assert scaling.crossover(costly)[("kkl", 20)] == [5]
    costly["us_per_step_batch1"] = 1.0  # as cheap as the EKF: not cheaper
    assert scaling.crossover(costly)[("kkl", 1)] == []


def test_report_states_exponents_crossovers_and_failures():
    study = frame()
    study.loc[3, ["status", "rmse"]] = ["MemoryError: 40 GB", math.nan]
    text = scaling.render_scaling(study, "standard")
    assert "| ekf         | 40  | failed: MemoryError: 40 GB |" in text
    assert "| kkl         | 3.00       | 2.00               | 0.50              |" in text
    assert "| ekf         | -          | 0.00               | 1.00              |" in text
    assert "| kkl         | every n    | every n   |" in text
