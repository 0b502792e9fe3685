"""The training loop's ledger: steps, samples and wall time, across a resume."""

import types

import pytest
import torch

from kkl_bench.kkl import optimize


class Interrupted(Exception):
    pass


@pytest.fixture
def clock(monkeypatch):
    """A wall clock that moves only when a loss is evaluated: one second per step."""
    now = types.SimpleNamespace(value=0.0)
    monkeypatch.setattr(optimize.time, "perf_counter", lambda: now.value)
    return now


def train(cache_dir, clock, steps, interrupt_at=None):
    """One resumable training of ``steps`` steps, checkpointed every 4; its ledger."""
    parameter = torch.nn.Parameter(torch.zeros(2))

    def loss(step):
        if step == interrupt_at:
            raise Interrupted
        clock.value += 1.0
        return ((parameter - 1.0) ** 2).sum()

    generator = torch.Generator().manual_seed(0)
    resumable = optimize.resumable(cache_dir, {"kind": "test"}, [generator], every=4)
    with resumable, optimize.counting() as spent:
        optimize.minimize(loss, [parameter], steps, samples_per_step=3)
        optimize.minimize(loss, [parameter], steps, samples_per_step=3)
    return spent


def test_the_ledger_counts_steps_samples_and_wall_time(tmp_path, clock):
    spent = train(tmp_path, clock, steps=10)
    assert spent.as_dict() == {"steps": 20, "samples": 60, "seconds": 20.0, "device": "cpu"}


def test_a_resumed_training_counts_the_time_spent_before_the_interruption(tmp_path, clock):
    with pytest.raises(Interrupted):
        train(tmp_path, clock, steps=10, interrupt_at=6)  # second call, checkpoint at step 4
    clock.value += 1000.0  # the machine sat idle between the kill and the rerun
    spent = train(tmp_path, clock, steps=10)
    # 10 s of the first call and 4 of the second before the checkpoint, 6 after the resume
    assert spent.seconds == 20.0
    assert (spent.steps, spent.samples) == (20, 60)
