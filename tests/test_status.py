"""What a running job says it does: status files written by the job, read by the command."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import torch

from kkl_bench.kkl.optimize import minimize
from kkl_bench.support import status


def test_a_job_states_what_it_does_and_its_file_goes_with_it(tmp_path):
    path = status.status_path(tmp_path, "ekf--vdp--seed0")
    since = time.time() - 1
    with status.reporting(path, "ekf on vdp, seed 0"):
        status.say("fitting")
        assert status.current(tmp_path, since) == ["ekf on vdp, seed 0: fitting"]
        status.say("scoring paper/zero (1/4)")
        assert status.current(tmp_path, since) == ["ekf on vdp, seed 0: scoring paper/zero (1/4)"]
    assert not path.exists() and status.current(tmp_path, since) == []
    status.say("outside any job")  # nobody listens: nothing is written
    assert list(tmp_path.iterdir()) == []


def test_a_file_older_than_the_run_is_not_shown(tmp_path):
    stale = status.status_path(tmp_path, "left-by-a-killed-run")
    stale.write_text(f"{status._WRITER}\ngru_observer on lorenz, seed 0: fitting")
    assert status.current(tmp_path, since=time.time() + 5) == []


def test_a_file_of_a_process_that_is_gone_is_not_shown(tmp_path):
    """A run killed after the reading run started leaves a newer file: its writer tells."""
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    since = time.time() - 1
    for job, writer in [("killed", f"{socket.gethostname()} {gone}"),
                        ("elsewhere", f"another-machine {gone}"), ("here", status._WRITER)]:  # fmt: skip
        status.status_path(tmp_path, job).write_text(f"{writer}\n{job}: fitting")
    assert status.current(tmp_path, since) == ["elsewhere: fitting", "here: fitting"]


def test_training_reports_its_steps_at_most_once_a_second_and_at_the_end(tmp_path, monkeypatch):
    clock = iter(range(0, 1000, 1))  # every call of the clock: 1/4 s later
    monkeypatch.setattr(status.time, "monotonic", lambda: next(clock) / 4)
    written, write = [], status._Status.write

    def recording(self, text):
        written.append(text)
        write(self, text)

    monkeypatch.setattr(status._Status, "write", recording)
    weight = torch.nn.Parameter(torch.ones(2))
    with status.reporting(status.status_path(tmp_path, "job"), "job"):
        minimize(lambda step: (weight**2).sum(), [weight], steps=12, samples_per_step=1,
                 description="decoder T*")  # fmt: skip
    assert written[-1] == "decoder T* 12/12"
    assert 2 <= len(written) <= 5  # 12 steps over 3 s of the fake clock: not every step
