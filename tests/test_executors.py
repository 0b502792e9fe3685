"""Parallel and distributed runs give the serial run's numbers; interrupted runs resume."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kkl_bench.run import harness
from kkl_bench.run.harness import RunSpec, run
from kkl_bench.run.results import cell_path, load_results
from kkl_bench.suite.task import get_profile
from kkl_bench.support import executors
from kkl_bench.support.executors import execute
from tests.repository import REPOSITORY

GRID = dict(
    estimators=("ekf",),
    systems=("duffing", "vdp"),
    regimes=("zero", "square"),
    profile=get_profile("quick"),
)


def numbers(results_dir):
    table = load_results(results_dir).sort_values(["system", "regime"])
    return table[
        ["system", "regime", "rmse", "smape", "nrmse", "per_state_rmse", "test_set_fingerprint"]
    ].to_dict("records")


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    results = tmp_path_factory.mktemp("serial")
    assert run(RunSpec(**GRID, results_dir=results)).ok
    return numbers(results)


def test_local_processes_reproduce_the_serial_numbers(tmp_path, serial):
    summary = run(RunSpec(**GRID, results_dir=tmp_path), jobs=2)
    assert summary.ok and len(summary.scored) == 4
    assert numbers(tmp_path) == serial


@pytest.mark.slow
def test_dask_local_cluster_reproduces_the_serial_numbers(tmp_path, serial):
    summary = run(RunSpec(**GRID, results_dir=tmp_path), jobs=2, executor="dask")
    assert summary.ok and len(summary.scored) == 4
    assert numbers(tmp_path) == serial


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(jobs=0), "jobs must be a positive integer, got 0"),
        (dict(executor="slurm"), "unknown executor 'slurm'; valid executors: loky, dask"),
        (dict(scheduler="tcp://x:1"), "--scheduler is for the dask executor"),
    ],
)
def test_bad_executor_arguments_are_clear_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        list(execute(print, [(1,)], **kwargs))


def run_command(results, *extra):
    return [
        sys.executable,
        "-m",
        "kkl_bench.cli",
        "run",
        "--estimator",
        "ekf",
        "ukf",
        "--system",
        "duffing",
        "vdp",
        "--profile",
        "quick",
        "--results",
        str(results),
        *extra,
    ]


CELLS = 2 * 2 * 4
"""Two filters on two systems, four regimes each."""


def cell_files(results):
    return sorted(Path(results).glob("*/*/*/*.json"))


def start_and_stop_part_way(results, sig):
    process = subprocess.Popen(
        run_command(results),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a test run started in the background of a non-interactive shell ignores
        # SIGINT, and the child would inherit that; give it the default handling
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while len(cell_files(results)) < 4:
        assert process.poll() is None, "the run ended before it could be interrupted"
        assert time.monotonic() < deadline
        time.sleep(0.05)
    process.send_signal(sig)
    process.wait(timeout=60)
    return process


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_an_interrupted_run_resumes_with_nothing_lost_or_duplicated(tmp_path, sig):
    process = start_and_stop_part_way(tmp_path, sig)
    if sig == signal.SIGINT:
        assert process.returncode == 130
        assert (
            "interrupted; every finished cell is saved; run the same command again to resume"
            in process.stderr.read()
        )
    before = {path: path.read_bytes() for path in cell_files(tmp_path)}
    assert 4 <= len(before) < CELLS
    for content in before.values():
        json.loads(content)  # every file on disk is a whole record
    resumed = subprocess.run(run_command(tmp_path), capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert (
        f"{CELLS - len(before)} cells scored, {len(before)} already done, 0 failed"
        in resumed.stdout
    )
    after = cell_files(tmp_path)
    assert len(after) == CELLS and len({(p.parent, p.name) for p in after}) == CELLS
    assert all(before[path] == path.read_bytes() for path in before)  # finished cells untouched
    assert set(load_results(tmp_path)["status"]) == {"ok"}


def job_whose_worker_dies_on_vdp(spec, job):
    """Runs the job, except that the worker process scoring vdp dies without a word."""
    if job.system == "vdp":
        other = [
            cell_path(spec.results_dir, job.estimator, "duffing", task.regime, "quick", 0)
            for task in job.tasks
        ]
        deadline = time.monotonic() + 60
        while not all(path.exists() for path in other) and time.monotonic() < deadline:
            time.sleep(0.1)  # let the other worker finish its job first
        os._exit(1)
    return harness.run_job(spec, job)


def test_a_dead_worker_keeps_finished_cells_and_records_the_rest(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(REPOSITORY), prepend=os.pathsep)
    monkeypatch.setattr(harness, "run_job", job_whose_worker_dies_on_vdp)
    summary = run(RunSpec(**GRID, results_dir=tmp_path), jobs=2)
    assert not summary.ok
    assert {(cell.system, cell.status) for cell in summary.scored + summary.failed} == {
        ("duffing", "ok"),
        ("vdp", "error"),
    }
    assert all("not completed" in cell.error for cell in summary.failed)
    assert set(load_results(tmp_path).groupby("system")["status"].first()) == {"ok", "error"}


def test_a_job_runs_on_one_thread_unless_told_within_its_share_of_the_cores(monkeypatch):
    """Under ``taskset -c 1`` a job asking for four threads gets one, not the machine's
    count; on four cores two jobs get one thread each by default, two if they ask."""
    monkeypatch.setattr(executors.os, "sched_getaffinity", lambda pid: {1}, raising=False)
    assert executors.threads_per_worker(1, threads=4) == 1
    monkeypatch.setattr(executors.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert executors.threads_per_worker(2) == 1
    assert executors.threads_per_worker(2, threads=4) == 2
    assert executors.threads_per_worker(8, threads=4) == 1


def test_a_job_run_in_this_process_is_limited_to_its_threads():
    import torch

    before = torch.get_num_threads()
    seen = list(executors.execute(lambda: torch.get_num_threads(), [()], jobs=1, threads=1))
    assert seen == [1] and torch.get_num_threads() == before


def test_a_job_waits_while_a_running_job_holds_a_name_no_finished_job_has_held():
    schedule = executors.Schedule(
        [frozenset({"P1"}), frozenset({"P1"}), frozenset(), frozenset({"P1"})]
    )
    assert schedule.start() == 0  # trains P1
    assert schedule.start() == 2  # job 1 would wait for job 0's P1: the next one starts
    assert schedule.start() is None  # jobs 1 and 3 both need P1
    schedule.finish(2)
    assert schedule.start() is None
    schedule.finish(0)  # P1 is saved: the jobs that load it may run together
    assert (schedule.start(), schedule.start(), schedule.start()) == (1, 3, None)


def started(folder, name):
    return (Path(folder) / f"{name}.started").exists()


def claim_job(folder, name):
    """Records when it starts and ends; job ``a`` ends once another job has started (or
    after a minute), so that a job started beside it is seen to be."""
    Path(folder, f"{name}.started").write_text(str(time.monotonic_ns()))
    if name == "a":
        deadline = time.monotonic() + 60
        while not (started(folder, "b") or started(folder, "c")) and time.monotonic() < deadline:
            time.sleep(0.01)
    Path(folder, f"{name}.ended").write_text(str(time.monotonic_ns()))
    return name


@pytest.mark.parametrize("executor", ["loky", pytest.param("dask", marks=pytest.mark.slow)])
def test_workers_run_a_job_that_shares_no_untrained_model_with_a_running_one(tmp_path, executor):
    """Jobs ``a`` and ``b`` claim one model, ``c`` none: with two workers ``c`` runs beside
    ``a``, and ``b`` starts only after ``a`` ended (given in the order a, b, c, first come
    first served would start ``b`` beside ``a``)."""
    claims = [{"model"}, {"model"}, set()]
    arguments = [(str(tmp_path), name) for name in "abc"]
    finished = list(execute(claim_job, arguments, jobs=2, executor=executor, claims=claims))
    assert sorted(finished) == ["a", "b", "c"]

    def time_of(name, event):
        return int((tmp_path / f"{name}.{event}").read_text())

    assert time_of("b", "started") > time_of("a", "ended")
    assert time_of("c", "started") < time_of("a", "ended")


def test_claims_are_one_per_job():
    with pytest.raises(ValueError, match="claims must be one per job: 1 for 2 jobs"):
        list(execute(print, [(1,), (2,)], jobs=2, claims=[{"model"}]))
