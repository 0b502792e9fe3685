"""A Phase-1 training killed part-way continues from its checkpoint and ends where an
uninterrupted training with the same seed ends."""

import os
import signal
import subprocess
import sys
import time

import pytest

SCRIPT = """
import hashlib, sys
from pathlib import Path

import torch

torch.set_num_threads(1)
from kkl_bench.estimator import FitContext
from kkl_bench.kkl import optimize
from kkl_bench.kkl.autonomous import Phase1Config, fit_autonomous
from kkl_bench.protocol import DT, N_SAMPLES, SIGMA_V, SIGMA_W
from kkl_bench.registry import systems
from kkl_bench.training import TrainingData

optimize.CHECKPOINT_EVERY = 50
steps = 0
adam_step = torch.optim.Adam.step


def counted_step(self, *args, **kwargs):
    global steps
    steps += 1
    return adam_step(self, *args, **kwargs)


torch.optim.Adam.step = counted_step
system = systems.get("duffing")()
context = FitContext(
    system=system, dt=DT, n_samples=N_SAMPLES, sigma_w=SIGMA_W, sigma_v=SIGMA_V,
    training=TrainingData(system, DT, N_SAMPLES, SIGMA_W, SIGMA_V, 0), seed=0,
    profile="quick", budget={}, cache_dir=Path(sys.argv[1]),
)
config = Phase1Config(
    hidden=16, train_trajectories=4, encoder_steps=2000, decoder_steps=200,
    selection_steps=60, batch=128, rate_candidates=((1.0, 5.0), (2.0, 10.0)),
)
model = fit_autonomous(context, config)
state = [*model.encoder.state_dict().values(), *model.decoder.state_dict().values()]
digest = hashlib.sha256(b"".join(t.numpy().tobytes() for t in state)).hexdigest()
print(digest, steps, model.spent["steps"])
"""
TOTAL_STEPS = 2 * 60 + 2000 + 200


def fit(script, cache):
    done = subprocess.run(
        [sys.executable, str(script), str(cache)], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    digest, steps, spent = done.stdout.split()
    return digest, int(steps), int(spent)


@pytest.mark.slow
def test_a_killed_phase1_resumes_from_its_checkpoint_with_the_same_result(tmp_path):
    script = tmp_path / "fit.py"
    script.write_text(SCRIPT)
    uninterrupted = fit(script, tmp_path / "reference")
    assert uninterrupted[1:] == (TOTAL_STEPS, TOTAL_STEPS)

    cache = tmp_path / "cache"
    process = subprocess.Popen(
        [sys.executable, str(script), str(cache)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    checkpoints = cache / "kkl-resume"
    deadline = time.monotonic() + 300
    # two rate-selection trainings finished (two slots each), the encoder's first checkpoint whole
    while len(list(checkpoints.glob("*.pt.sha256"))) < 5 and time.monotonic() < deadline:
        assert process.poll() is None, "the training ended before it could be killed"
        time.sleep(0.02)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (cache / "kkl-phase1").exists() or not list((cache / "kkl-phase1").glob("*.pt"))

    resumed = fit(script, cache)
    assert resumed[0] == uninterrupted[0]  # bit for bit the same maps
    assert resumed[1] < TOTAL_STEPS - 2 * 60  # it did not start again from nothing
    assert resumed[2] == TOTAL_STEPS  # and it reports the whole training's budget
    assert list(checkpoints.glob("*.pt")) == []  # checkpoints removed once the model is saved
