"""Budget tables by system, and by system and measurement model (the hard track's fits)."""

from dataclasses import dataclass

import pytest

from kkl_bench.kkl.config import budget_keys, from_budget
from kkl_bench.measurement import MeasurementModel, NoiseLaw
from kkl_bench.run.spec import FitConditions, conditioned_context
from kkl_bench.suite.task import get_profile
from tests import repository


@dataclass(frozen=True)
class Steps:
    rnn_steps: int = 1


STEPS = {"default": 2000, "vdp": 3000, "vdp:sampling": 4000}
PROTOCOL = MeasurementModel()
RECURRENT_ROWS = ("gru_observer", "kalmannet", "ring_observer")


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


def test_the_protocol_states_the_standard_profiles_caps():
    """Section 6's paragraph on training budgets names the cap of each training as the
    `standard` profile sets it (the profile holds caps; the plateau rule ends a training)."""
    protocol = repository.PROTOCOL.read_text()
    start = protocol.index("Training budgets (decision of this project")
    paragraph = " ".join(protocol[start : protocol.index("\n\n", start)].split())
    profile = get_profile("standard")
    kkl = profile.budget_for()
    gru, kalmannet, ring = (profile.budget_for(row) for row in RECURRENT_ROWS)
    stated = [
        f"Phase 1's encoder {kkl['encoder_steps']} steps and its decoder {kkl['decoder_steps']},",
        f"the hypernetworks' Phase 2 {kkl['phase2_steps']},",
        f"each of `curriculum_kkl`'s levels {kkl['curriculum_steps']},",
        f"`injection_kkl`'s decoder adaptation {kkl['adaptation_steps']} over",
        f"`gru_observer` (no Phase 1) {gru['rnn_steps']} steps of {gru['rnn_batch']} "
        f"trajectories x {gru['rnn_window']} samples",
        f"`kalmannet` {kalmannet['rnn_steps']} steps of {kalmannet['rnn_batch']} "
        f"trajectories x {kalmannet['rnn_window']} samples",
        f"`ring_observer` {ring['rnn_steps']} of about {ring['ring_site_batch']} site "
        f"histories x {ring['rnn_window']} samples",
    ]
    assert [text for text in stated if text not in paragraph] == []
