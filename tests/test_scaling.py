"""The scaling study's arithmetic: cell summaries, fitted exponents, crossovers, the report."""

import math
import re
import shutil

import numpy as np
import pandas as pd
import pytest

from kkl_bench.analysis import scaling, scaling_timing
from kkl_bench.cli import main
from kkl_bench.report import markdown
from kkl_bench.report.scaling import study_section, write_study
from kkl_bench.suite.task import get_profile
from kkl_bench.support import convergence
from tests.repository import BOARD

REGIMES = ("zero", "constant", "sinusoid", "square")


def cells(estimator, n, rmse, fit_time, status="ok", regimes=REGIMES, report=None):
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
    assert summary.loc[("big", 10), "status"] == "error"
    assert summary.loc[("big", 10), "reason"] == "MemoryError: 40 GB"
    assert math.isnan(summary.loc[("big", 10), "rmse"])
    assert summary.loc[("ekf", 5), "converged"] == ""  # nothing trained
    assert len(summary) == 4
    summary = scaling.cell_summary(results[results["system"] != "lorenz96-n10"])
    assert set(summary["n"]) == {5}  # no size is invented
    only_ekf_at_10 = results[
        (results["estimator"] == "ekf") | (results["system"] != "lorenz96-n10")
    ]
    summary = scaling.cell_summary(only_ekf_at_10).set_index(["estimator", "n"])
    assert summary.loc[("big", 10), "status"] == scaling.NOT_RUN
    assert summary.loc[("big", 10), "reason"] == "no result stored"
    assert math.isnan(summary.loc[("big", 10), "rmse"])
    half_run = results[(results["estimator"] != "ekf") | results["regime"].isin(["zero", "square"])]
    summary = scaling.cell_summary(half_run).set_index(["estimator", "n"])
    assert summary.loc[("ekf", 5), "status"] == scaling.NOT_RUN
    assert summary.loc[("ekf", 5), "reason"] == "no result for constant, sinusoid"
    assert math.isnan(summary.loc[("ekf", 5), "rmse"])
    with pytest.raises(ValueError, match="no more-systems cells of lorenz96-n5"):
        scaling.cell_summary(results[results["track"] == "paper"])


def test_a_row_whose_regimes_come_from_two_fits_is_not_run():
    """A ``--force`` rerun cut off after two regimes leaves cells of two trainings."""
    old, new = {"spent": {"decoder": {"seconds": 9.0}}}, {"spent": {"decoder": {"seconds": 8.0}}}
    mixed = cells("big", 5, 0.2, 30.0, regimes=REGIMES[:2], report=new)
    mixed += cells("big", 5, 0.3, 31.0, regimes=REGIMES[2:], report=old)
    other_seed = [{**cell, "seed": 1} for cell in cells("big", 5, 0.3, 30.0, report=old)]
    summary = scaling.cell_summary(pd.DataFrame(mixed + other_seed)).set_index(["estimator", "n"])
    assert summary.loc[("big", 5), "status"] == scaling.NOT_RUN
    assert summary.loc[("big", 5), "reason"].startswith("its cells come from 2 fits")
    assert summary.loc[("big", 5), "overwrite"]
    one_fit = cells("big", 5, 0.2, 30.0, report=new) + other_seed
    summary = scaling.cell_summary(pd.DataFrame(one_fit)).set_index(["estimator", "n"])
    assert summary.loc[("big", 5), "status"] == "ok"  # a seed per fit is not a mix
    assert not summary.loc[("big", 5), "overwrite"]


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
                    reason=None,
                    rmse=0.1,
                    nrmse=0.01,
                    fit_time_s=fit[i],
                    converged="" if name == "ekf" else "yes",
                    overwrite=False,
                    timing_run=1,
                    timing_commit="abc",
                    us_per_step_batch20=batch20[i],
                    us_per_step_batch1=batch1[i],
                    ekf_us_per_step_batch20=300.0,
                    ekf_us_per_step_batch1=400 * size / 5.0,
                )
            )
    return scaling.with_ratios(pd.DataFrame(rows))


def test_only_estimators_that_train_have_fit_times_to_plot():
    study = frame()
    fit_times = scaling.trained_fit_times(study)
    assert fit_times[study["estimator"] == "ekf"].isna().all()  # 1 ms: building a model
    assert fit_times[study["estimator"] == "kkl"].tolist() == [10.0, 80.0, 640.0, 5120.0]


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
    costly["us_per_step_batch1"] = 1.0
    costly["ekf_us_per_step_batch1"] = 1.0  # as cheap as the EKF: not cheaper
    assert scaling.crossover(costly)[("kkl", 1)] == []


def test_crossover_compares_each_row_with_the_ekf_of_its_own_timing_run():
    study = frame()
    late = (study["estimator"] == "kkl") & (study["n"] == 40)
    # kkl at n = 40 costs 128 at batch 20, timed later on a machine where the EKF took 100
    study.loc[late, ["timing_run", "ekf_us_per_step_batch20"]] = [2, 100.0]
    assert scaling.crossover(study)[("kkl", 20)] == [5, 10, 20]


def test_crossover_with_the_local_filter_compares_costs_of_one_run_only():
    study = frame()
    local = study[study["estimator"] == "ekf"].assign(estimator=scaling.LOCAL_FILTER)
    local["us_per_step_batch20"] = [1.0, 10.0, 100.0, 1000.0]  # kkl: 2, 8, 32, 128
    local.loc[local["n"] == 40, "timing_run"] = 2  # timed in another run than kkl's
    study = pd.concat([study, local], ignore_index=True)
    assert scaling.crossover(study, scaling.LOCAL_FILTER)[("kkl", 20)] == [10, 20]
    text = render_scaling(study, "standard")
    assert f"and than `{scaling.LOCAL_FILTER}` timed in the same run" in text
    assert "| kkl | every n timed | every n timed | n = 10, 20 | every n timed |" in squeezed(text)


def timings(pairs, cost, engines=("numpy",)):
    """time_estimators' frame: every (estimator, n) at both batches on each of ``engines``,
    costing ``cost(name, n)`` (``cost(name, n, engine)`` with several engines)."""
    return pd.DataFrame(
        [
            {
                "estimator": name,
                "n": n,
                "engine": engine,
                "engine_used": engine,
                "batch": batch,
                "us_per_step": (cost(name, n, engine) if len(engines) > 1 else cost(name, n))
                * batch,
            }
            for name, n in pairs
            for engine in engines
            for batch in scaling.BATCHES
        ]
    )


def test_a_filter_is_timed_on_its_compiled_engine_with_its_reference_engine_beside():
    pairs = [("ekf", 40), ("kkl", 40)]
    reference = {"compiled": 1.0, "reference": 50.0}
    frame = scaling_timing.timing_frame(
        timings(pairs, lambda name, n, engine: reference[engine], ("compiled", "reference"))
        .query("estimator == 'ekf' or engine == 'compiled'")
        .assign(engine_used=lambda f: f["engine"].where(f["estimator"] == "ekf", "torch")),
        commit="abc",
    ).set_index(["estimator", "n"])
    assert frame.loc[("ekf", 40), "engine"] == "compiled"
    assert frame.loc[("ekf", 40), "us_per_step_batch20"] == 20.0
    assert frame.loc[("ekf", 40), "reference_engine_us_per_step_batch20"] == 1000.0
    assert frame.loc[("kkl", 40), "engine"] == "torch"  # one engine: no reference beside
    assert math.isnan(frame.loc[("kkl", 40), "reference_engine_us_per_step_batch20"])
    assert frame.loc[("kkl", 40), "ekf_us_per_step_batch20"] == 20.0  # the compiled EKF
    study = scaling.scaling_frame(
        pd.DataFrame(
            [
                {"estimator": name, "n": 40, "status": "ok", "rmse": 0.1, "fit_time_s": 1.0,
                 "converged": "", "reason": None, "nrmse": 0.1, "overwrite": False}
                for name in ("ekf", "kkl")
            ]
        ),
        frame.reset_index(),
    )  # fmt: skip
    text = render_scaling(study, "standard")
    assert "`ekf`: timed on the compiled engine, the reference engine's cost beside it" in text
    assert "| 20 (reference 1e+03) |" in text


def test_a_later_timing_run_adds_the_missing_rows_beside_its_own_ekf(tmp_path):
    pairs = [("ekf", 5), ("ekf", 10), ("kkl", 5)]
    first = scaling_timing.timing_frame(timings(pairs, lambda _, n: n), commit="1234e56")
    assert first.set_index(["estimator", "n"]).loc[("kkl", 5), "ekf_us_per_step_batch20"] == 100
    results = pd.DataFrame(
        cells("ekf", 5, 0.1, 0.0)
        + cells("ekf", 10, 0.1, 0.0)
        + cells("kkl", 5, 0.2, 9.0)
        + cells("kkl", 10, 0.3, 9.0)
        + cells("gru", 10, math.nan, math.nan, status="error")
    )
    summary = scaling.cell_summary(results)
    write_study(summary, first, "standard", tmp_path)
    stored = scaling_timing.stored_timings(tmp_path / "scaling.csv")
    pd.testing.assert_frame_equal(stored, first, check_dtype=False)

    # kkl at n = 10 was fitted since; the failed gru cell is not timed
    wanted = scaling_timing.untimed(summary, stored)
    assert wanted == [("ekf", 10), ("kkl", 10)]
    second = scaling_timing.timing_frame(
        timings(wanted, lambda name, n: 3 * n if name == "ekf" else n), commit="f00d"
    )
    merged = scaling_timing.add_timings(stored, second).set_index(["estimator", "n"])
    assert merged.loc[("kkl", 10), "timing_run"] == 2
    assert merged.loc[("kkl", 10), "ekf_us_per_step_batch20"] == 600  # its run's EKF
    assert merged.loc[("ekf", 10), "us_per_step_batch20"] == 200  # the stored EKF stays
    assert merged.loc[("ekf", 10), "timing_run"] == 1
    study = scaling.scaling_frame(summary, merged.reset_index()).set_index(["estimator", "n"])
    assert study.loc[("kkl", 10), scaling.RMSE_RATIO] == pytest.approx(3.0)  # 0.3 / 0.1
    assert study.loc[("kkl", 10), list(scaling.SPEEDUPS)].tolist() == [3.0, 3.0]  # its run's EKF
    assert study.loc[("kkl", 5), list(scaling.SPEEDUPS)].tolist() == [1.0, 1.0]
    text = render_scaling(study.reset_index(), "standard")
    row = next(line for line in text.splitlines() if line.startswith("| kkl         | 10 "))
    assert [cell.strip() for cell in row.split("|")[-4:-1]] == ["3", "3", "3"]
    assert (
        "Timing run 2 (code of commit f00d) added `kkl` at n = 10, beside the EKF at the same sizes (EKF in run 2: "
        "n = 10: 600 and 30 µs/step at batch 20 and 1 (run 1: 200 and 10))." in text
    )
    assert scaling_timing.untimed(summary, merged.reset_index()) == []
    assert "| kkl         | 0.58   | 0.00       | 1.00 †             | 1.00 †            |" in text
    assert "† fitted to online costs from more than one timing run" in text


def test_a_study_written_before_timing_runs_were_recorded_reads_as_run_one(tmp_path):
    legacy = frame().drop(
        columns=["timing_run", "ekf_us_per_step_batch20", "ekf_us_per_step_batch1"]
    )
    legacy.to_csv(tmp_path / "scaling.csv", index=False)
    stored = scaling_timing.stored_timings(tmp_path / "scaling.csv").set_index(["estimator", "n"])
    assert (stored["timing_run"] == 1).all()
    models = stored["models"].unstack("n")
    assert (models.loc["kkl"] == "trained").all()  # every study before timed the cache's
    assert (models.loc["ekf"] == "").all()  # a filter has no models to time
    assert stored.loc[("kkl", 40), "ekf_us_per_step_batch1"] == pytest.approx(3200.0)
    assert scaling_timing.stored_timings(None).empty
    assert scaling_timing.stored_timings(tmp_path / "absent.csv").empty


def test_report_states_exponents_crossovers_and_failures():
    study = frame()
    study.loc[3, ["status", "reason", "rmse"]] = ["error", "MemoryError: 40 GB", math.nan]
    text = render_scaling(study, "standard")
    assert "| ekf         | 40  | failed: MemoryError: 40 GB |" in text
    assert "| kkl | 40 | 0.1 | 5,120 | yes |" in squeezed(text)  # fit times in whole seconds
    assert "| ekf | 20 | 0.1 | 0 | |" in squeezed(text)
    study.loc[7, ["status", "reason", "rmse"]] = ["unsupported", "too big here", math.nan]
    text = render_scaling(study, "standard")
    assert "| kkl         | 40  | unsupported " in text
    assert "- `kkl` at n = 40: too big here" in text
    never_run = study.copy()
    never_run.loc[7, ["status", "reason", "rmse"]] = [scaling.NOT_RUN, "no result", math.nan]
    text = render_scaling(never_run, "standard")
    assert "| kkl         | 40  | not run " in text
    assert (
        '- `kkl` at n = 40: no result; `kkl-bench run --estimator "kkl" --track more-systems '
        "--profile standard --system lorenz96-n40`"
    ) in text
    never_run.loc[7, "overwrite"] = True
    assert "--system lorenz96-n40 --force`" in render_scaling(never_run, "standard")
    assert "| Converged " in text and "| yes " in text
    assert "| kkl         | 0.00   | 3.00       | 2.00               | 0.50              |" in text
    assert "| ekf         | 0.00   | -          | 0.00               | 1.00              |" in text
    assert "| kkl | every n timed | every n timed |" in squeezed(text)
    study.loc[study["estimator"] == "kkl", "us_per_step_batch1"] = math.nan
    study.loc[(study["estimator"] == "kkl") & (study["n"] == 40), "us_per_step_batch20"] = math.nan
    study.loc[(study["estimator"] == "kkl") & (study["n"] == 20), "us_per_step_batch20"] = 1e9
    text = render_scaling(study, "standard")
    assert "| kkl | n = 5, 10 | not timed |" in squeezed(text)
    study.loc[study["estimator"] == "kkl", "us_per_step_batch20"] *= 1e9
    text = render_scaling(study, "standard")  # timed up to n = 20, not at 40
    assert "| kkl | never up to n = 20 | not timed |" in squeezed(text)


def render_scaling(frame, profile):
    return markdown.section(study_section(frame, profile))


def squeezed(text):
    """``text`` with every run of spaces as one (a table's cells whatever their widths)."""
    return re.sub(" +", " ", text)


def test_curve_frame_gives_each_training_once_at_the_size_it_trained_at(tmp_path):
    def report(trained_on=None):
        curve = {"validation_curve": [[0, 1.0], [50, 0.2], [100, 0.1]]}
        return {"training_log": curve, **({"trained_on": trained_on} if trained_on else {})}

    results = pd.DataFrame(
        cells("ring", 5, 0.1, 9.0, report=report())
        + cells("ring", 10, 0.1, 9.0, report=report())
        + cells("moved", 5, 0.1, 9.0, report=report("lorenz96-n10"))
        + cells("moved", 10, 0.1, 9.0, report=report("lorenz96-n10"))
        + cells("ekf", 5, 0.1, 0.0)
    )
    curves = scaling.curve_frame(results)
    assert sorted(set(zip(curves["estimator"], curves["n"], strict=True))) == [
        ("moved", 10),
        ("ring", 5),
        ("ring", 10),
    ]
    assert curves[curves["estimator"] == "moved"]["error"].tolist() == [1.0, 0.2, 0.1]
    written = write_study(
        scaling.cell_summary(results),
        scaling_timing.stored_timings(None),
        "standard",
        tmp_path,
        curves,
    )
    assert (tmp_path / "figures" / "scaling-curves.png") in written
    assert (
        "![validation curves](figures/scaling-curves.png)" in (tmp_path / "scaling.md").read_text()
    )


def test_a_later_run_at_a_new_size_gives_the_ekf_costs_once():
    study = frame()
    study.loc[study["n"] == 40, "timing_run"] = 2  # the EKF and kkl first timed at 40 in run 2
    text = render_scaling(study, "standard")
    assert "(EKF in run 2: n = 40: 300 and 3.2e+03 µs/step at batch 20 and 1)." in text


def test_a_timing_run_of_untrained_models_is_recorded_and_said():
    pairs = [("ekf", 5), ("autonomous_kkl", 5)]
    summary = pd.DataFrame(
        [
            {"estimator": name, "n": 5, "status": "ok", "rmse": 0.1, "fit_time_s": 1.0,
             "converged": "", "reason": None, "nrmse": 0.1, "overwrite": False}
            for name, _ in pairs
        ]
    )  # fmt: skip
    texts = {}
    for models in scaling.MODELS:
        frame = scaling_timing.timing_frame(timings(pairs, lambda name, n: 2.0), "abc", models)
        rows = frame.set_index("estimator")["models"]
        assert rows.to_dict() == {"autonomous_kkl": models, "ekf": ""}  # a filter has none
        texts[models] = render_scaling(scaling.scaling_frame(summary, frame), "standard")
    assert "timed on untrained models" in texts["untrained"]
    assert "untrained" not in texts["trained"]


def test_untrained_models_take_the_published_fits_choices(tmp_path):
    """An injection gain of zero chosen on data skips the injection: the untrained model
    must skip it too, whatever gain its cut-short training would choose."""
    spec = scaling_timing.RunSpec(
        ("injection_kkl",), ("lorenz96-n5",), ("sinusoid",), get_profile("quick"),
        tracks=(scaling.TRACK,), cache_dir=tmp_path,
    )  # fmt: skip
    report = {"training_log": {"injection_gain": 0.0}}
    results = pd.DataFrame(cells("injection_kkl", 5, 0.1, 1.0, report=report))
    published = scaling_timing.published_report(results, "injection_kkl", 5, seed=0)
    assert published == report
    assert scaling_timing.published_report(results, "injection_kkl", 10, seed=0) == {}
    (fitted,) = scaling_timing.fit_untrained(spec, "injection_kkl", 5, 0, published).values()
    assert fitted.gain_ == 0.0
    last_steps = {curve[-1][0] for _, curve in convergence.curves(fitted.fit_report())}
    assert 2 + scaling_timing.UNTRAINED_STEPS in last_steps  # Phase 1's trainings were cut short


@pytest.mark.skipif(not (BOARD / "scaling.md").exists(), reason="no committed study here")
def test_the_committed_study_is_what_the_code_renders_from_the_committed_results(tmp_path):
    """scaling.md and scaling.csv as ``--render-only`` writes them from ``leaderboard/results``
    and the study's stored online costs: a cell rescored, or a change to the report, is
    committed with the study rendered again."""
    pytest.importorskip("matplotlib")  # it draws the study's figures too
    shutil.copy(BOARD / "scaling.csv", tmp_path)  # its stored timings
    rendered = ["scaling", "--render-only", "--results", str(BOARD / "results")]
    assert main([*rendered, "--out", str(tmp_path)]) == 0
    for name in ("scaling.md", "scaling.csv"):
        assert (tmp_path / name).read_bytes() == (BOARD / name).read_bytes(), (
            f"leaderboard/{name} is not what `kkl-bench scaling --render-only --results "
            "leaderboard/results` writes with this code: render it again"
        )
