"""`kkl-bench regenerate`: the plan read from a results folder, its estimate, and a run
interrupted and resumed that makes each cell once."""

import io
import json
import multiprocessing
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest
import torch
from tqdm import tqdm

from kkl_bench.cli import main
from kkl_bench.cli.run import following
from kkl_bench.report.provenance import core_hours_per_row, regeneration_sentence
from kkl_bench.run import harness, ledger, regenerate
from kkl_bench.run.harness import Job
from kkl_bench.run.results import load_results, read_cell, trained_models, write_cell
from kkl_bench.suite.task import Task, get_profile
from tests.git_repo import commit_all, git

PROFILE = get_profile("quick")


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A results folder of two rows (the EKF on three cells, the UKF on two)."""
    results = tmp_path_factory.mktemp("published")
    for estimator, regimes in (
        ("ekf", ["zero", "sinusoid", "square"]),
        ("ukf", ["zero", "square"]),
    ):
        argv = ["run", "--estimator", estimator, "--system", "duffing", "--regime", *regimes]
        assert main([*argv, "--results", str(results)]) == 0
    return results


def test_the_plan_covers_the_source_cells_and_counts_their_recorded_cost(published, tmp_path):
    source = load_results(published)
    planned = regenerate.plan(source, PROFILE, tmp_path / "into", tmp_path / "cache")
    assert planned.cells == 5 and planned.done == 0
    assert [(p.job.estimator, [t.regime for t in p.job.tasks]) for p in planned.jobs] == [
        ("ekf", ["zero", "sinusoid", "square"]),
        ("ukf", ["zero", "square"]),
    ]
    for planned_job in planned.jobs:  # the fit time and scoring time its cells recorded
        cells = source[source["estimator"] == planned_job.job.estimator]
        scoring = (cells["estimate_us_per_step"] * 1e-6 * cells["n_test"] * 1001).sum()
        fit = cells["fit_time_s"].iloc[0]
        assert planned_job.estimate_s == pytest.approx(fit + scoring)
    assert all(planned_job.trains for planned_job in planned.jobs)
    assert "2 jobs of 2 rows to make 5 cells (0 of 5 already done): 2 fits, 0 scoring only" in (
        planned.describe()
    )
    assert {planned_job.spec.device for planned_job in planned.jobs} == {"cpu"}
    elsewhere = regenerate.plan(source, PROFILE, tmp_path / "into", tmp_path / "c", device="auto")
    assert {planned_job.spec.device for planned_job in elsewhere.jobs} == {"auto"}


def test_a_model_several_jobs_share_is_counted_once():
    spent = {"phase1": {"steps": 9, "seconds": 100.0}, "phase2": {"steps": 9, "seconds": 10.0}}
    cells = [
        {
            "estimator": row,
            "task": f"duffing/{regime}@v1",
            "seed": 0,
            "fit_report": {"spent": report},
        }
        for row, regime, report in (
            ("a", "zero", spent),
            ("a", "square", spent),
            ("b", "zero", {**spent, "phase2": {"steps": 9, "seconds": 20.0}}),
        )
    ]
    frame = pd.DataFrame(cells).assign(
        system="duffing", estimate_us_per_step=float("nan"), fit_time_s=1.0
    )
    records = regenerate._CostRecords(frame)
    zero, square = Task("duffing", "zero"), Task("duffing", "square")
    assert records.seconds(Job("a", "duffing", (zero,), 0)) == (110.0, 0.0)
    assert records.seconds(Job("b", "duffing", (zero,), 0)) == (20.0, 0.0)
    phase1 = ("duffing", 0, "phase1", 100.0)  # what the jobs that share it name it
    assert records.models(Job("a", "duffing", (zero,), 0)) == {
        phase1,
        ("duffing", 0, "phase2", 10.0),
    }
    assert records.models(Job("b", "duffing", (zero,), 0)) == {
        phase1,
        ("duffing", 0, "phase2", 20.0),
    }
    resumed = regenerate._CostRecords(frame)
    resumed.made([("a", "duffing/zero@v1", 0)])  # a's cell is done: its models are trained
    assert resumed.seconds(Job("b", "duffing", (zero,), 0)) == (20.0, 0.0)
    assert resumed.seconds(Job("a", "duffing", (square,), 0)) == (0.0, 0.0)  # a only scores
    assert resumed.models(Job("b", "duffing", (zero,), 0)) == {("duffing", 0, "phase2", 20.0)}
    assert resumed.models(Job("a", "duffing", (square,), 0)) == frozenset()


def test_a_model_is_named_by_the_phases_that_trained_at_their_recorded_seconds():
    spent = {
        "phase1": {"steps": 500, "seconds": 9.0, "processor_seconds": 8.5, "device": "cpu"},
        "phase2": {"steps": 300, "seconds": 4.0, "device": "cuda"},  # wall time off the CPU
        "adaptation": {"steps": 0, "seconds": 0.2},  # took no step: loaded, or none asked
    }
    learned = SimpleNamespace(system="vdp", seed=1, fit_report={"spent": spent})
    assert trained_models(learned) == {("vdp", 1, "phase1", 8.5), ("vdp", 1, "phase2", 4.0)}
    a_filter = SimpleNamespace(system="vdp", seed=1, fit_report={}, fit_time_s=0.02)
    assert trained_models(a_filter) == frozenset()  # its fit trains nothing to share


def test_a_regeneration_holds_back_the_jobs_that_share_a_model_not_trained_yet(
    published, tmp_path, monkeypatch
):
    planned = regenerate.plan(load_results(published), PROFILE, tmp_path, tmp_path / "cache")
    shared = ("duffing", 0, "fit", 1.0)
    planned = regenerate.Plan(
        [replace(job, models=frozenset({shared})) for job in planned.jobs], 5, 0
    )
    given, execute = [], regenerate.execute

    def recording(function, arguments, *args, claims=None):
        given.append(claims)
        return execute(function, arguments, *args, claims=claims)

    monkeypatch.setattr(regenerate, "execute", recording)
    regenerate.run(planned, tmp_path)
    assert given == [[{shared}, {shared}]]
    assert len(load_results(tmp_path)) == 5


def test_a_job_that_only_scores_is_counted_as_such_and_keeps_its_scoring_estimate():
    job = Job("ekf", "duffing", (Task("duffing", "zero"),), 0)
    scoring_only = regenerate.PlannedJob(None, job, fit_s=0.0, scoring_s=5.0, rate=3.0)
    fit = regenerate.PlannedJob(None, job, fit_s=10.0, scoring_s=5.0, rate=3.0)
    assert not scoring_only.trains and scoring_only.expected_s == 5.0
    assert fit.trains and fit.expected_s == 35.0  # the measured rate scales the training only
    described = regenerate.Plan([scoring_only, fit], cells=2, done=0).describe()
    assert "2 jobs of 1 rows to make 2 cells (0 of 2 already done): 1 fits, 1 scoring only" in (
        described
    )
    assert "  ekf: 1 fits, 1 scoring only, 0.01 core-hours" in described
    vdp = regenerate.PlannedJob(None, Job("ekf", "vdp", job.tasks, 0), fit_s=7200.0, scoring_s=0.0)
    described = regenerate.Plan([scoring_only, fit, vdp], cells=3, done=0).describe()
    assert "Per system, estimated: vdp 2.0, duffing 0.0 core-hours (`--system`" in described


def test_a_resumed_plan_counts_each_row_s_fits_left_at_the_rate_its_finished_fits_took(
    published, tmp_path
):
    into = tmp_path / "into"
    planned = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    assert planned.rates is None and planned.expected_s == planned.estimate_s
    finished = {"seconds": 30.0, "wall_seconds": 40.0, "cells": 1, "failed": 0}
    into.mkdir()
    (into / ledger.LEDGER_FILE).write_text(
        json.dumps(
            {
                "jobs": {  # two finished EKF fits of other seeds: 6 and 1.2 times their estimates, 2 over both
                    "ekf duffing seed7 [duffing/zero@v1]": {**finished, "estimate_s": 5.0},
                    "ekf duffing seed8 [duffing/zero@v1]": {**finished, "estimate_s": 25.0},
                }
            }
        )
    )
    resumed = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    assert resumed.rates.by_row == {"ekf": 2.0} and resumed.rates.overall == 2.0
    ekf, ukf = resumed.jobs
    assert (ekf.rate, ukf.rate) == (2.0, 1.0)  # the UKF has no finished fit: its estimate
    assert resumed.expected_s == pytest.approx(2 * ekf.fit_s + ekf.scoring_s + ukf.estimate_s)
    described = resumed.describe()
    assert (
        "The 2 jobs finished in this folder took 2.00 times their estimates; per row: ekf 2.00."
        in described
    )


def test_a_row_s_rate_on_a_track_counts_its_jobs_of_that_track(published, tmp_path):
    """A track's source cells were trained under budgets of their own, so a row's rate is
    taken per track where its jobs there finished, and over all its tracks elsewhere."""
    finished = {"wall_seconds": 1.0, "cells": 1, "failed": 0}
    into = tmp_path / "into"
    into.mkdir()
    (into / ledger.LEDGER_FILE).write_text(
        json.dumps(
            {
                "jobs": {  # the EKF at 2 times its estimate on the paper track, 10 on hard
                    "ekf duffing seed7 [duffing/zero@v1]": {
                        **finished, "seconds": 20.0, "estimate_s": 10.0
                    },
                    "ekf duffing seed7 [hard/duffing/sparse-sinusoid@v1]": {
                        **finished, "seconds": 100.0, "estimate_s": 10.0
                    },
                }
            }
        )
    )  # fmt: skip
    resumed = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    rates = resumed.rates
    assert rates.by_track == {("ekf", "paper"): 2.0, ("ekf", "hard"): 10.0}
    assert rates.by_row == {"ekf": 6.0} and rates.overall == 6.0
    assert (rates.rate("ekf", "hard"), rates.rate("ekf", "far-init"), rates.rate("ukf")) == (
        10.0,
        6.0,  # no finished job of that track: the row's rate over its tracks
        1.0,
    )
    ekf, _ = resumed.jobs  # the fixture's EKF cells are of the paper track
    assert ekf.rate == 2.0
    assert "per row: ekf 6.00 (paper 2.00, hard 10.00)." in resumed.describe()


def test_a_ledger_key_names_its_row_even_with_a_variant():
    key = regenerate.job_key(
        Job("particle_filter[n=20000]", "lorenz", (Task("lorenz", "zero"),), 2)
    )
    assert regenerate._row_of(key) == "particle_filter[n=20000]"
    assert regenerate._track_of(key) == "paper"
    hard = regenerate.job_key(Job("ekf", "vdp", (Task("vdp", "sparse-sinusoid", track="hard"),), 0))
    assert regenerate._track_of(hard) == "hard"
    with pytest.raises(ValueError, match="not a regeneration ledger key"):
        regenerate._row_of("ekf")


def test_an_interrupted_regeneration_resumes_and_makes_each_cell_once(
    published, tmp_path, capsys, monkeypatch
):
    into = tmp_path / "into"
    argv = ["regenerate", "--from", str(published), "--into", str(into), "--profile", "quick"]
    calls = []
    original = harness.run_job

    def interrupted_after_one_job(spec, job):
        if calls:
            raise KeyboardInterrupt
        calls.append(job.estimator)
        return original(spec, job)

    with monkeypatch.context() as patched:
        patched.setattr(harness, "run_job", interrupted_after_one_job)
        assert main(argv) == 130
    assert calls == ["ekf"]
    first = json.loads((into / ledger.LEDGER_FILE).read_text())["jobs"]
    assert [record["cells"] for record in first.values()] == [3]

    assert main(argv) == 0  # resumed: the UKF's job only
    out = capsys.readouterr().out
    assert "1 jobs of 1 rows to make 2 cells (3 of 5 already done): 1 fits" in out
    written = json.loads((into / ledger.LEDGER_FILE).read_text())["jobs"]
    assert sorted(record["cells"] for record in written.values()) == [2, 3]
    cells = load_results(into)
    assert len(cells) == 5 and not cells.duplicated(["estimator", "task", "seed"]).any()
    assert set(cells["status"]) == {"ok"}
    assert main(argv) == 0  # nothing left to do
    assert "0 jobs of 0 rows to make 0 cells (5 of 5 already done)" in capsys.readouterr().out
    summary = ledger.ledger_summary(ledger.read_ledger(into))
    assert summary["jobs"] == 2 and summary["cells"] == 5 and summary["core_hours"] > 0


def test_a_cell_decided_unsupported_is_kept_and_not_planned_again(tmp_path):
    source, into = tmp_path / "source", tmp_path / "into"
    argv = ["run", "--estimator", "ring_observer", "--system", "duffing", "--regime", "zero"]
    assert main([*argv, "--results", str(source)]) == 0
    regeneration = ["regenerate", "--from", str(source), "--into", str(into), "--profile", "quick"]
    assert main(regeneration) == 0
    assert list(load_results(into)["status"]) == ["unsupported"]
    planned = regenerate.plan(load_results(source), PROFILE, into, tmp_path / "cache")
    assert planned.jobs == [] and planned.done == planned.cells == 1


def test_regenerate_refuses_its_source_as_target_and_unknown_names(published, capsys):
    base = ["regenerate", "--from", str(published), "--profile", "quick"]
    assert main([*base, "--into", str(published)]) == 2
    assert "is the source folder" in capsys.readouterr().err
    assert main([*base, "--into", "elsewhere", "--estimator", "enkf", "--dry-run"]) == 2
    assert "hold no estimator 'enkf'; valid: ekf, ukf" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_regenerate_on_cuda_without_a_gpu_is_an_error_before_any_work(published, tmp_path, capsys):
    argv = ["regenerate", "--from", str(published), "--into", str(tmp_path / "into")]
    assert main([*argv, "--profile", "quick", "--device", "cuda"]) == 2
    assert "torch sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "into").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_regeneration_on_the_gpu_says_so_in_its_ledger(published, tmp_path):
    into = tmp_path / "into"
    argv = ["regenerate", "--from", str(published), "--into", str(into), "--profile", "quick"]
    assert main([*argv, "--estimator", "ekf", "--device", "cuda"]) == 0
    written = ledger.read_ledger(into)
    assert {record["device"] for record in written["jobs"].values()} == {"cuda"}
    assert ledger.ledger_summary(written)["gpu_jobs"] == 1


METER_CHILD = """
import sys, time
from kkl_bench.run.ledger import metered
with metered(sys.argv[1], sys.argv[2], every_s=0.02):
    end = time.process_time() + 0.3
    while time.process_time() < end:  # spend processor time, then say so
        pass
    time.sleep(0.1)  # a meter write after the spending
    print("spent", flush=True)
    time.sleep(60)
"""


def _metered_child(folder, key):
    """A process that spends 0.3 s of processor time under a meter of ``key``, says so, and
    waits to be killed."""
    child = subprocess.Popen(
        [sys.executable, "-c", METER_CHILD, str(folder), key], stdout=subprocess.PIPE, text=True
    )
    assert child.stdout.readline() == "spent\n"
    return child


def _record_jobs(folder, writer, count):
    """``count`` finished jobs of one regeneration, recorded in the ledger of ``folder``."""
    for index in range(count):
        times = {"seconds": 1.0, "wall_seconds": 1.0}
        ledger.record_job(Path(folder), f"job {writer}-{index}", times, 1.0, 1, 0)


def test_regenerations_into_one_folder_at_once_lose_none_of_each_other_s_jobs(tmp_path):
    context = multiprocessing.get_context("spawn")
    writers = [context.Process(target=_record_jobs, args=(tmp_path, w, 40)) for w in range(4)]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(timeout=120)
        assert writer.exitcode == 0
    assert len(ledger.read_ledger(tmp_path)["jobs"]) == 4 * 40


def test_a_killed_job_s_meter_counts_once_and_a_live_one_is_left(tmp_path):
    key = "kalmannet duffing seed0 [duffing/zero@v1]"
    live = _metered_child(tmp_path, key)
    try:
        assert ledger.interrupted_times(tmp_path, key) == {"seconds": 0.0, "wall_seconds": 0.0}
        killed = _metered_child(tmp_path, key)
        killed.kill()
        killed.wait()
        (banked,) = ledger.killed_attempts(tmp_path, key)  # read, left in place
        spent = ledger.interrupted_times(tmp_path, key)
        assert 0.3 <= spent["seconds"] < 1.0 and spent == banked
        assert spent["wall_seconds"] >= spent["seconds"] + 0.05  # its sleep, metered
        assert ledger.interrupted_times(tmp_path, key)["seconds"] == 0.0  # counted once
        assert len(list(tmp_path.glob(f"{ledger.METER_FOLDER}/*/*.json"))) == 1  # the live one
    finally:
        live.kill()
        live.wait()


def test_a_killed_attempt_s_meter_is_committed_with_the_results_and_counted_in_a_clone(tmp_path):
    """A new machine gets the results folder from git: the killed attempt's meter goes with
    it (only the locks are ignored), and the job resumed there counts its time."""
    key = "gru_observer vdp seed2 [vdp/zero@v1]"
    results = tmp_path / "board" / "results"
    killed = _metered_child(results, key)
    killed.kill()
    killed.wait()
    (banked,) = ledger.killed_attempts(results, key)

    commit_all(tmp_path / "board", "the refit so far")
    git("clone", "-q", str(tmp_path / "board"), str(tmp_path / "clone"), cwd=tmp_path)
    cloned = tmp_path / "clone" / "results"
    assert not list(cloned.glob(f"{ledger.METER_FOLDER}/*/*.lock"))
    assert ledger.interrupted_times(cloned, key) == banked


def test_the_work_done_counts_processor_time_and_a_job_past_its_estimate_grows_the_total(
    tmp_path,
):
    def planned(seed, fit_s, banked_s=0.0):
        job = Job("kalmannet", "duffing", (Task("duffing", "zero"),), seed)
        return regenerate.PlannedJob(None, job, fit_s, scoring_s=0.0, banked_s=banked_s)

    long, short = planned(0, 100.0, banked_s=5.0), planned(1, 0.1)
    plan = regenerate.Plan([long, short], cells=2, done=0)
    done = regenerate.WorkDone(plan, tmp_path, time.time_ns())
    assert done.measure() == (5.0, 100.1)  # before anything runs: the killed attempt's work
    children = [_metered_child(tmp_path, job.key) for job in (long, short)]
    try:  # each has spent 0.3 s under its meter; the short job, expected 0.1 s, grows the total
        spent, total = done.measure()
        assert 5.6 <= spent < 6.5
        assert 100.3 <= total < 101.0  # the long job's 100 s, and the short one's 0.3 s
        ledger.record_job(tmp_path, long.key, {"seconds": 80.0, "wall_seconds": 90.0}, 100, 1, 0)
        done.finish(long)  # at what the ledger records: 20 s less than expected
        spent, total = done.measure()
        assert 80.3 <= spent < 81.0 and total == spent
        later = regenerate.WorkDone(plan, tmp_path, time.time_ns())
        assert later.measure() == (5.0, 100.1)  # meters of attempts started before it
    finally:
        for child in children:
            child.kill()
            child.wait()


def test_a_bar_follows_measured_work_and_its_total():
    bar = tqdm(total=10.0, file=io.StringIO())
    measured = [(4.0, 10.0)]
    with following(bar, lambda: measured[0], every_s=0.01) as update:
        time.sleep(0.1)
        assert (bar.n, bar.total) == (4.0, 10.0)  # set by the thread
        measured[0] = (12.0, 15.0)  # a job ran past its estimate
        update()
        assert (bar.n, bar.total) == (12.0, 15.0)
    bar.close()


def test_a_finished_job_adds_its_killed_attempts_time_to_the_ledger(published, tmp_path):
    into = tmp_path / "into"
    planned = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    first = planned.jobs[0].key
    meters = ledger._meter_folder(into, first)
    meters.mkdir(parents=True)  # what a killed attempt of the first job left
    (meters / "elsewhere-1-1.json").write_text('{"seconds": 1000.0, "wall_seconds": 2000.0}')
    resumed = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    assert [job.banked_s for job in resumed.jobs] == [1000.0, 0.0]
    spent, total = regenerate.WorkDone(resumed, into, time.time_ns()).measure()
    assert spent == 1000.0 and total == 1000.0 + resumed.jobs[1].expected_s  # past its estimate
    assert "1 of the jobs resume killed attempts, which spent 0.28 core-hours" in resumed.describe()
    jobs = regenerate.run(resumed, into)["jobs"]
    assert 1000 < jobs[first]["seconds"] < 1100 and 2000 < jobs[first]["wall_seconds"] < 2100
    other = planned.jobs[1].key
    assert jobs[other]["seconds"] < 100
    left = sorted(path.name for path in meters.parent.iterdir())
    assert left == [".gitignore", "ledger.lock"]  # no meter; the ledger's lock, ignored by git


def test_a_job_resumed_after_its_killed_attempt_wrote_a_cell_counts_that_cell_and_its_time(
    published, tmp_path
):
    into = tmp_path / "into"
    planned = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    whole = planned.jobs[0]  # the EKF's fit, on three cells
    # what an attempt killed while it scored left: its first cell, and its meter
    ekf = whole.job
    harness.run_job(whole.spec, Job(ekf.estimator, ekf.system, ekf.tasks[:1], ekf.seed))
    meters = ledger._meter_folder(into, whole.key)
    meters.mkdir(parents=True)
    (meters / "elsewhere-1-1.json").write_text('{"seconds": 1000.0, "wall_seconds": 2000.0}')
    resumed = regenerate.plan(load_results(published), PROFILE, into, tmp_path / "cache")
    first = resumed.jobs[0]
    assert first.job.tasks == ekf.tasks[1:] and first.key == whole.key  # the attempt's key
    assert first.banked_s == 1000.0 and first.earlier_cells == 1
    jobs = regenerate.run(resumed, into)["jobs"]
    assert jobs[whole.key]["cells"] == 3 and 1000 < jobs[whole.key]["seconds"] < 1100
    assert ledger.ledger_summary(ledger.read_ledger(into))["cells"] == 5


def test_a_job_run_again_for_its_failed_cell_counts_each_cell_once(tmp_path):
    key = "ekf duffing seed0 [duffing/zero@v1,duffing/square@v1]"
    ledger.record_job(tmp_path, key, {"seconds": 2.0, "wall_seconds": 3.0}, 5.0, 2, failed=1)
    ledger.record_job(tmp_path, key, {"seconds": 1.0, "wall_seconds": 1.0}, 5.0, 1, failed=0)
    (record,) = ledger.read_ledger(tmp_path)["jobs"].values()
    assert record["cells"] == 2 and record["failed"] == 0
    assert record["seconds"] == 3.0 and record["wall_seconds"] == 4.0


def test_the_board_says_how_many_of_its_cells_the_regeneration_wrote(published, tmp_path):
    into = tmp_path / "into"
    regenerate.run(regenerate.plan(load_results(published), PROFILE, into, tmp_path / "c"), into)
    written = ledger.read_ledger(into)
    assert {record["device"] for record in written["jobs"].values()} == {"cpu"}
    summary = ledger.ledger_summary(written)
    assert regeneration_sentence(summary, 5).startswith(
        "Written by `kkl-bench regenerate`: all 5 cells, by 2 jobs (fits, and jobs that only "
    )
    assert summary["gpu_jobs"] == 0 and "GPU" not in regeneration_sentence(summary, 5)
    first = next(iter(written["jobs"].values()))
    first["device"] = "cuda"
    del next(reversed(written["jobs"].values()))["device"]  # a ledger from before: the CPU
    on_gpu = ledger.ledger_summary(written)
    assert on_gpu["gpu_jobs"] == 1
    assert "one thread a job; 1 of the jobs ran with `--device cuda`, whose GPU time this " in (
        regeneration_sentence(on_gpu, 5)
    )
    part = regeneration_sentence(summary, 12)
    assert "5 of the 12 cells (the others' runs are listed below), by 2 jobs" in part
    assert "not written by `kkl-bench regenerate`" in regeneration_sentence(None, 12)


def test_the_board_says_where_the_core_hours_went_per_row(tmp_path):
    def record(key, hours, estimated_hours, cells):
        times = {"seconds": hours * 3600, "wall_seconds": hours * 3600}
        ledger.record_job(tmp_path, key, times, estimated_hours * 3600, cells, 0)

    record("ekf duffing seed0 [duffing/zero@v1]", 0.5, 0.25, 4)
    record("autonomous_kkl duffing seed0 [duffing/zero@v1,duffing/square@v1]", 1.0, 2.0, 2)
    record("autonomous_kkl lorenz seed0 [hard/lorenz/sparse-zero@v1]", 3.0, 1.0, 1)
    record("autonomous_kkl duffing seed1 [duffing/zero@v1]", 2.5, 1.0, 1)  # Duffing: 3.5
    rows = ledger.ledger_summary(ledger.read_ledger(tmp_path))["rows"]
    assert rows == [
        {
            "row": "autonomous_kkl",
            "jobs": 3,
            "cells": 4,
            "core_hours": 6.5,
            "estimated_core_hours": 4.0,
            "costliest_system": "duffing",
            "costliest_core_hours": 3.5,
        },
        {
            "row": "ekf",
            "jobs": 1,
            "cells": 4,
            "core_hours": 0.5,
            "estimated_core_hours": 0.25,
            "costliest_system": "duffing",
            "costliest_core_hours": 0.5,
        },
    ]
    text, table = core_hours_per_row(ledger.ledger_summary(ledger.read_ledger(tmp_path)))
    assert "counts in the job that trained it" in text.markdown
    assert list(table.frame["costliest"]) == ["duffing (3.50)", "duffing (0.50)"]
    assert core_hours_per_row(None) == []


def test_a_job_scoring_many_tasks_keeps_a_meter_of_its_own(tmp_path):
    tasks = [f"noise/duffing/constant-sigma0.{i:03d}@v1" for i in range(30)]
    first, second = (f"autonomous_kkl duffing seed0 [{','.join(tasks[i:])}]" for i in (0, 1))
    with ledger.metered(tmp_path, first), ledger.metered(tmp_path, second):
        assert len(list(tmp_path.glob(f"{ledger.METER_FOLDER}/*/*.json"))) == 2
    assert ledger.interrupted_times(tmp_path, first) == {"seconds": 0.0, "wall_seconds": 0.0}


@pytest.fixture
def at_commit(monkeypatch):
    """Set the commit that provenance reports (cells, ledger jobs and --redo read it)."""
    from kkl_bench.support import provenance as module

    recorded = module._static_provenance()

    def set_commit(commit):
        monkeypatch.setattr(
            module, "_static_provenance", lambda: {**recorded, "git_commit": commit}
        )

    return set_commit


@pytest.fixture
def regenerated(published, tmp_path, at_commit):
    """The published cells regenerated into a folder at commit a1: the folder, the source
    and the EKF's cell files."""
    into, source = tmp_path / "into", load_results(published)
    at_commit("0000000000a1")
    regenerate.run(regenerate.plan(source, PROFILE, into, tmp_path / "c"), into)
    return into, source, sorted((into / "quick" / "ekf").rglob("*.json"))


def test_a_redo_makes_a_row_s_cells_of_another_commit_again_and_keeps_their_jobs_apart(
    regenerated, tmp_path, at_commit
):
    into, source, ekf_cells = regenerated
    assert len(ekf_cells) == 3

    at_commit("0000000000b2")  # the EKF's training changed
    dry = regenerate.redo(source, PROFILE, into, ["ekf"], "a new cap", dry_run=True)
    assert sorted(dry.cells) == ekf_cells and len(dry.jobs) == 1
    assert "--redo ekf would make 3 cells again (those not written at 0000000000b2)" in (
        dry.describe()
    )
    assert (
        all(path.exists() for path in ekf_cells)
        and ledger.read_ledger(into).get("superseded") is None
    )
    planned = regenerate.plan(source, PROFILE, into, tmp_path / "c", recompute=dry.cells)
    assert [(p.job.estimator, len(p.job.tasks)) for p in planned.jobs] == [("ekf", 3)]
    assert planned.done == 2 and all(path.exists() for path in ekf_cells)

    done = regenerate.redo(source, PROFILE, into, ["ekf"], "a new cap")
    assert done.jobs == dry.jobs and not any(path.exists() for path in ekf_cells)
    written = ledger.read_ledger(into)
    (superseded,) = written["superseded"]
    assert superseded["key"] == dry.jobs[0] and superseded["because"] == "a new cap"
    assert superseded["cells"] == 3 and list(written["jobs"]) == [
        key for key in written["jobs"] if key.startswith("ukf ")
    ]

    resumed = regenerate.plan(source, PROFILE, into, tmp_path / "c")
    assert [(p.job.estimator, len(p.job.tasks)) for p in resumed.jobs] == [("ekf", 3)]
    assert resumed.done == 2
    taken = superseded["seconds"] / superseded["estimate_s"]  # priced at what it took before
    assert resumed.jobs[0].rate == pytest.approx(taken)
    assert f"all made again at the rate those took (ekf {taken:.2f})" in resumed.describe()
    regenerate.run(resumed, into)
    again = regenerate.redo(source, PROFILE, into, ["ekf"], "a new cap")
    assert again.cells == () and again.jobs == ()  # what this commit made stays

    summary = ledger.ledger_summary(ledger.read_ledger(into))
    assert summary["jobs"] == 2 and summary["cells"] == 5
    assert summary["commits"] == {"0000000000a1": 2, "0000000000b2": 3}  # cells, in order
    assert "at commits 0000000000a1 (2 cells), 0000000000b2 (3 cells), the jobs" in (
        regeneration_sentence(summary, 5)
    )
    assert summary["superseded"]["jobs"] == 1 and summary["superseded"]["because"] == ["a new cap"]
    assert summary["superseded"]["core_hours"] == superseded["seconds"] / 3600
    assert "Besides, 1 earlier jobs took 0.0 core-hours whose cells were made again at a " in (
        regeneration_sentence(summary, 5)
    )
    assert regeneration_sentence(summary, 5).endswith("later commit (a new cap).")


def test_a_capped_only_redo_makes_again_just_the_jobs_whose_fit_reached_a_cap(
    regenerated, tmp_path, at_commit
):
    into, source, ekf_cells = regenerated
    cell = read_cell(ekf_cells[0])
    report = {"training_log": {"stopped": "cap", "steps": 16000}}
    write_cell(into, replace(cell, fit_report=report))
    before = {path: path.read_bytes() for path in into.rglob("*.json")}

    at_commit("0000000000b2")  # a cap raised
    done = regenerate.redo(source, PROFILE, into, ["ekf", "ukf"], "a cap", capped_only=True)
    # the capped cell, and the other two cells of its job (one fit); the UKF's stay
    assert sorted(done.cells) == ekf_cells and not any(path.exists() for path in ekf_cells)
    assert [key.split()[0] for key in done.jobs] == ["ekf"]
    assert "(those whose fit reached a cap and not written at 0000000000b2)" in done.describe()
    assert all(path.read_bytes() == data for path, data in before.items() if "ukf" in path.parts)
    assert list(ledger.read_ledger(into)["jobs"]) == [
        key for key in ledger.read_ledger(into)["jobs"] if key.startswith("ukf ")
    ]
    resumed = regenerate.plan(source, PROFILE, into, tmp_path / "c")
    assert [(p.job.estimator, len(p.job.tasks)) for p in resumed.jobs] == [("ekf", 3)]


def test_a_redo_refuses_uncommitted_code_and_a_folder_no_regeneration_wrote(
    published, tmp_path, at_commit
):
    source = load_results(published)
    at_commit("0000000000b2-dirty")
    with pytest.raises(
        ValueError, match="the code must be a clean commit; it is 0000000000b2-dirty"
    ):
        regenerate.redo(source, PROFILE, published, ["ekf"], "why")
    at_commit("0000000000b2")
    with pytest.raises(ValueError, match="holds no ledger of a regeneration"):
        regenerate.redo(source, PROFILE, published, ["ekf"], "why")
    ledger.record_job(tmp_path, "ekf duffing seed0 [duffing/zero@v1]", {"seconds": 1.0}, 1.0, 1, 0)
    with pytest.raises(ValueError, match="hold no estimator 'enkf'; valid: ekf, ukf"):
        regenerate.redo(source, PROFILE, tmp_path, ["enkf"], "why")


def test_redo_and_because_go_together(published, tmp_path, capsys):
    argv = ["regenerate", "--from", str(published), "--into", str(tmp_path), "--profile", "quick"]
    assert main([*argv, "--redo", "ekf", "--dry-run"]) == 2
    assert "--redo ROW... and --because TEXT go together" in capsys.readouterr().err
    assert main([*argv, "--capped-only", "--dry-run"]) == 2
    assert "--capped-only narrows --redo ROW...: name the rows" in capsys.readouterr().err
