"""The training loop's ledger: steps, samples and wall time, across a resume."""

import types

import pytest
import torch

from kkl_bench import convergence
from kkl_bench.kkl import optimize
from kkl_bench.results import provenance


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
    assert spent.as_dict() == {
        "steps": 20,
        "samples": 60,
        "seconds": 20.0,
        "device": "cpu",
        "git_commit": provenance()["git_commit"],
    }


def test_the_ledger_names_the_commit_that_trained(tmp_path, clock, monkeypatch):
    monkeypatch.setattr(optimize, "provenance", lambda: {"git_commit": "0123abcd-dirty"})
    assert train(tmp_path, clock, steps=2).as_dict()["git_commit"] == "0123abcd-dirty"


def test_a_resumed_training_counts_the_time_spent_before_the_interruption(tmp_path, clock):
    with pytest.raises(Interrupted):
        train(tmp_path, clock, steps=10, interrupt_at=6)  # second call, checkpoint at step 4
    clock.value += 1000.0  # the machine sat idle between the kill and the rerun
    spent = train(tmp_path, clock, steps=10)
    # 10 s of the first call and 4 of the second before the checkpoint, 6 after the resume
    assert spent.seconds == 20.0
    assert (spent.steps, spent.samples) == (20, 60)


def test_the_validation_curve_is_measured_before_training_and_at_every_tenth(tmp_path, clock):
    parameter = torch.nn.Parameter(torch.zeros(1))
    calls = []

    def validation():
        calls.append(parameter.item())
        return abs(1.0 - parameter.item())

    training = optimize.minimize(
        lambda step: ((parameter - 1.0) ** 2).sum(),
        [parameter],
        25,
        1,
        lr=0.1,
        validation=validation,
    )
    steps = [step for step, _ in training.validation]
    assert steps == [0, 3, 6, 9, 12, 15, 18, 21, 24, 25]  # ceil(25 / 10) = 3
    assert training.validation[0][1] == 1.0 and len(training.losses) == 25
    log = training.log()
    assert log["validation_curve"][-1] == [25, training.validation[-1][1]]
    assert log["converged"] is convergence.converged(training.validation)


def test_a_resumed_training_keeps_its_validation_curve(tmp_path, clock):
    def run(interrupt_at=None):
        parameter = torch.nn.Parameter(torch.zeros(1))

        def loss(step):
            if step == interrupt_at:
                raise Interrupted
            return ((parameter - 1.0) ** 2).sum()

        generator = torch.Generator().manual_seed(0)
        with optimize.resumable(tmp_path, {"kind": "curve"}, [generator], every=4):
            return optimize.minimize(
                loss, [parameter], 10, 1, lr=0.1, validation=lambda: float(parameter.item())
            )

    whole = run()
    with pytest.raises(Interrupted):
        run(interrupt_at=6)  # checkpoint at step 4
    assert run().validation == whole.validation


@pytest.mark.parametrize(
    ("curve", "expected"),
    [
        ([(0, 1.0), (50, 0.40), (75, 0.39), (100, 0.385)], True),  # second half: -3.75 %
        ([(0, 1.0), (50, 0.40), (75, 0.38), (100, 0.37)], False),  # -7.5 %: still improving
        ([(0, 1.0), (25, 0.3), (50, 0.35), (100, 0.36)], True),  # rose again: converged
        ([(0, 0.3), (50, 37.2), (100, 37.2)], False),  # driven to its clip bounds: flat
        ([(0, 1.0), (100, 0.5)], None),  # too short to say
        ([(0, 1.0), (75, float("nan")), (100, 0.5)], False),  # diverged on the way
    ],
)
def test_the_convergence_rule_reads_the_second_half(curve, expected):
    assert convergence.converged(curve) is expected


@pytest.mark.parametrize(
    ("curve", "expected"),
    [
        ([(0, 1.0), (50, 0.40), (100, 0.30)], "no"),  # still falling: more steps may help
        ([(0, 0.3), (50, 37.2), (100, 37.2)], "diverged"),  # at its clip bounds
        ([(0, 1.0), (50, 0.3), (100, 0.61)], "diverged"),  # ended above twice its best
        ([(0, 1.0), (50, 0.3), (100, 0.59)], "yes"),  # rose, but by less than that
        ([(0, 1.0), (75, float("inf")), (100, 0.5)], "diverged"),
        ([(0, 1.0), (100, 0.5)], "not recorded"),
    ],
)
def test_each_training_is_judged_yes_no_or_diverged(curve, expected):
    assert convergence.outcome(curve) == expected
