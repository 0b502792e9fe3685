"""Training configurations read from a profile's budget.

A budget value may be a number or a table by system name with a
``default`` (e.g. ``hidden = {default = 64, lorenz = 128}``). A fit for a measurement
model other than the protocol's (the ``hard`` track's per-task fits) first looks for the
system's name followed by what its measurement model changes (``FEATURES``, sorted, joined
by ``+``): ``rnn_steps = {default = 2000, "vdp:sampling" = 4000}`` gives Van der Pol's
fits for sparse samples 4000 steps and every other fit of Van der Pol the default.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from kkl_bench.estimator import FitContext

C = TypeVar("C")


def from_budget(config_class: type[C], context: FitContext, **overrides: Any) -> C:
    """An instance of the dataclass ``config_class`` from ``context.budget``, then ``overrides``.

    Budget keys that are not fields of ``config_class`` are ignored (they
    belong to other phases).
    """
    values = {}
    for field in dataclasses.fields(config_class):
        if field.name not in context.budget:
            continue
        value = context.budget[field.name]
        if isinstance(value, dict):
            value = _entry(field.name, value, context)
        values[field.name] = tuple(map(tuple, value)) if isinstance(value, list) else value
    return config_class(**{**values, **overrides})


def budget_keys(context: FitContext) -> list[str]:
    """The keys a budget table is read at for ``context``, first found first: the system
    with its measurement model's features (a fit for another measurement model than the
    protocol's), the system, ``default``."""
    system = context.system.name
    features = sorted(context.measurement.features)
    return [*([f"{system}:{'+'.join(features)}"] if features else []), system, "default"]


def _entry(name: str, table: dict[str, Any], context: FitContext) -> Any:
    """The value of the budget table ``table`` (key ``name``) for ``context``."""
    keys = budget_keys(context)
    for key in keys:
        if key in table:
            return table[key]
    raise ValueError(f"budget {name!r} has no entry for any of {', '.join(map(repr, keys))}")
