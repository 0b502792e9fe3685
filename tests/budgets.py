"""Training budgets for tests whose checks do not need a trained model."""

from typing import Any

from kkl_bench import variants
from kkl_bench.suite.task import get_profile

FEW_STEPS = {
    **{key: 20 for key in ("encoder_steps", "decoder_steps", "selection_steps", "phase2_steps")},
    **{key: 20 for key in ("adaptation_steps", "rnn_steps")},
    "curriculum_steps": 10,
    "validate_every": 5,
}
"""Cuts the quick budget to a few optimizer steps (the filters read none of these keys)."""


def few_steps(estimator: str) -> dict[str, Any]:
    """The quick profile's budget for ``estimator`` (a name or variant), cut to
    :data:`FEW_STEPS`: what a conformance check asks of a fit (shapes, causality,
    determinism, finite estimates) does not depend on how well it trained."""
    return {**get_profile("quick").budget_for(variants.base_name(estimator)), **FEW_STEPS}
