"""Training configurations read from a profile's budget.

A budget value may be a number or a table by system name with a
``default`` (e.g. ``hidden = {default = 64, lorenz = 128}``).
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
            if "default" not in value and context.system.name not in value:
                raise ValueError(
                    f"budget {field.name!r} has no entry for {context.system.name!r} and no default"
                )
            value = value.get(context.system.name, value.get("default"))
        values[field.name] = tuple(map(tuple, value)) if isinstance(value, list) else value
    return config_class(**{**values, **overrides})
