"""The training loop's ledger: steps, samples, wall and processor time, across a resume."""

import types

import pytest
import torch

from kkl_bench.kkl import optimize
from kkl_bench.kkl.plateau import Plateau, PlateauRule
from kkl_bench.support import convergence
from kkl_bench.support.provenance import provenance


class Interrupted(Exception):
    pass


@pytest.fixture
def clock(monkeypatch):
    """Clocks that move only when a loss is evaluated: one second of wall time per step
    (``value``), half a second of processor time (``processor``)."""
    now = types.SimpleNamespace(value=0.0, processor=0.0)
    monkeypatch.setattr(optimize.time, "perf_counter", lambda: now.value)
    monkeypatch.setattr(optimize.time, "process_time", lambda: now.processor)
    return now


def train(cache_dir, clock, steps, interrupt_at=None):
    """One resumable training of ``steps`` steps, checkpointed every 4; its ledger."""
    parameter = torch.nn.Parameter(torch.zeros(2))

    def loss(step):
        if step == interrupt_at:
            raise Interrupted
        clock.value += 1.0
        clock.processor += 0.5
        return ((parameter - 1.0) ** 2).sum()

    generator = torch.Generator().manual_seed(0)
    resumable = optimize.resumable(cache_dir, {"kind": "test"}, [generator], every=4)
    with resumable, optimize.counting() as spent:
        optimize.minimize(loss, [parameter], steps, samples_per_step=3)
        optimize.minimize(loss, [parameter], steps, samples_per_step=3)
    return spent


def test_the_ledger_counts_steps_samples_wall_and_processor_time(tmp_path, clock):
    spent = train(tmp_path, clock, steps=10)
    assert spent.as_dict() == {
        "steps": 20,
        "samples": 60,
        "seconds": 20.0,
        "processor_seconds": 10.0,
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
    assert (spent.seconds, spent.processor_seconds) == (20.0, 10.0)
    assert (spent.steps, spent.samples) == (20, 60)


def test_without_a_rule_the_validation_curve_is_measured_at_every_tenth(tmp_path, clock):
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


RULE = PlateauRule(
    validate_every=2, plateau_patience=3, plateau_tolerance=0.01, plateau_reductions=2
)


def scripted(errors):
    """A training of one parameter whose validation errors are ``errors`` in turn; returns
    the parameter, the value it held at each measurement, and ``minimize``'s loss,
    parameters and validation."""
    parameter = torch.nn.Parameter(torch.zeros(1))
    errors, held = iter(errors), []

    def validation():
        held.append(parameter.item())
        return next(errors)

    def loss(step):
        return ((parameter - 100.0) ** 2).sum()  # moves the parameter at every step

    return parameter, held, (loss, [parameter], validation)


def test_a_plateau_lowers_the_rate_then_stops_the_training_and_keeps_the_best():
    # falls, then flat: three measurements without 1 % progress make a plateau
    errors = [1.0, 0.5, 0.3, 0.2, 0.2, 0.199, 0.2, 0.198, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2]
    parameter, held, (loss, parameters, validation) = scripted(errors)
    training = optimize.minimize(
        loss, parameters, 1000, 1, lr=0.1, validation=validation, rule=RULE
    )
    # measured at steps 0, 2, ..., reductions after the 3rd and 6th measurement without
    # progress (steps 12 and 18), and the plateau after the second reduction stops it
    log = training.log()
    assert [step for step, _ in training.validation] == list(range(0, 26, 2))[:13]
    assert log["lr_reductions"] == [12, 18] and log["stopped"] == "plateau"
    assert log["converged"] is True and log["steps"] == 24 == len(training.losses)
    assert log["best_step"] == 14 and log["best_error"] == 0.198
    assert parameter.item() == held[7]  # the parameters of the best measurement
    assert convergence.outcomes(log) == ["yes"]


def test_a_rise_restores_the_best_state():
    errors = [1.0, 0.4, 0.6, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 1.5]
    parameter, held, (loss, parameters, validation) = scripted(errors)
    training = optimize.minimize(
        loss, parameters, 1000, 1, lr=0.1, validation=validation, rule=RULE
    )
    assert training.plateau["best_step"] == 2 and parameter.item() == held[1]
    assert training.kept_error == 0.4 != training.validation[-1][1]


def test_a_curve_still_falling_at_the_cap_says_so():
    errors = [1.0 * 0.9**k for k in range(11)]
    parameter, held, (loss, parameters, validation) = scripted(errors)
    training = optimize.minimize(loss, parameters, 20, 1, lr=0.1, validation=validation, rule=RULE)
    log = training.log()
    assert log["stopped"] == "cap" and log["converged"] is False and log["steps"] == 20
    assert log["best_step"] == 20 and parameter.item() == held[-1]
    assert convergence.outcomes(log) == ["no"]


def test_a_slow_steady_fall_adds_up_to_progress():
    """0.6 % a measurement never beats the last by 1 %, but beats the last that did."""
    rule = PlateauRule(validate_every=1, plateau_patience=2, plateau_reductions=0)
    plateau = Plateau(rule, [])
    actions = [plateau.measure(step, 0.994**step) for step in range(12)]
    assert "stop" not in actions and plateau.without_progress <= 1


def test_a_validation_error_that_is_not_finite_stops_the_training_as_diverged():
    parameter, held, (loss, parameters, validation) = scripted([1.0, 0.5, float("nan")])
    training = optimize.minimize(
        loss, parameters, 1000, 1, lr=0.1, validation=validation, rule=RULE
    )
    assert training.plateau["stopped"] == "diverged" and parameter.item() == held[1]
    assert convergence.outcomes(training.log()) == ["diverged"]


def test_a_rule_needs_a_validation_error():
    parameter = torch.nn.Parameter(torch.zeros(1))
    with pytest.raises(ValueError, match="needs a validation error"):
        optimize.minimize(lambda step: parameter.sum(), [parameter], 10, 1, rule=RULE)


@pytest.mark.parametrize("rule", [None, RULE], ids=["cosine", "plateau"])
def test_a_resumed_training_keeps_its_validation_curve(tmp_path, clock, rule):
    def run(interrupt_at=None):
        parameter = torch.nn.Parameter(torch.zeros(1))

        def loss(step):
            if step == interrupt_at:
                raise Interrupted
            return ((parameter - 1.0) ** 2).sum()

        generator = torch.Generator().manual_seed(0)
        with optimize.resumable(tmp_path / str(rule), {"kind": "curve"}, [generator], every=4):
            training = optimize.minimize(
                loss,
                [parameter],
                40,
                1,
                lr=0.1,
                validation=lambda: round(abs(1.0 - parameter.item()), 2),
                rule=rule,
            )
        return training, parameter.item()

    whole = run()
    with pytest.raises(Interrupted):
        run(interrupt_at=6)  # checkpoint at step 4
    resumed = run()
    assert resumed[0].validation == whole[0].validation and resumed[1] == whole[1]
    assert resumed[0].plateau == whole[0].plateau


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


def test_a_pause_counts_in_the_wall_time_only(clock):
    parameter = torch.nn.Parameter(torch.zeros(1))

    def loss(step):
        clock.value += 1000.0 if step == 3 else 1.0  # stopped (SIGSTOP) for 999 s at step 3
        clock.processor += 0.5
        return ((parameter - 1.0) ** 2).sum()

    with optimize.counting() as spent:
        optimize.minimize(loss, [parameter], 10, samples_per_step=1)
    assert (spent.seconds, spent.processor_seconds) == (1009.0, 5.0)
