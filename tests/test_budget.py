"""Budget tables by system, and by system and measurement model (the hard track's fits)."""

from dataclasses import dataclass

import pytest

from kkl_bench.kkl.config import budget_keys, from_budget
from kkl_bench.measurement import MeasurementModel, NoiseLaw
from kkl_bench.run.spec import FitConditions, conditioned_context


@dataclass(frozen=True)
class Steps:
    rnn_steps: int = 1


STEPS = {"default": 2000, "vdp": 3000, "vdp:sampling": 4000}
PROTOCOL = MeasurementModel()


def steps_for(system, measurement=PROTOCOL, table=STEPS):
    context = conditioned_context(
        system, 0, FitConditions(measurement), budget={"rnn_steps": table}
    )
    return from_budget(Steps, context).rnn_steps


def test_a_fit_for_another_measurement_model_reads_its_own_entry_first():
    sparse = MeasurementModel(observe_every=10)
    assert steps_for("vdp", sparse) == 4000
    assert steps_for("vdp") == 3000  # the protocol's measurement: the system's entry
    assert steps_for("duffing", sparse) == 2000  # no entry of its own: the default
    outliers = MeasurementModel(noise=NoiseLaw(law="outliers"))
    context = conditioned_context("vdp", 0, FitConditions(outliers))
    assert budget_keys(context) == ["vdp:noise", "vdp", "default"]
    assert steps_for("vdp", outliers) == 3000


def test_a_table_without_the_systems_entry_or_a_default_names_the_keys_it_tried():
    with pytest.raises(ValueError, match="'vdp:sampling', 'vdp', 'default'"):
        steps_for("vdp", MeasurementModel(observe_every=10), {"lorenz": 1})
