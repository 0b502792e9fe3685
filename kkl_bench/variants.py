"""Estimator variants: a registered estimator with non-default hyperparameters, named
in the parametrized style of benchopt, ``static_hyperkkl[guard=True]``.

A variant is a row of its own everywhere: ``run`` and ``check`` accept the
name, results are stored under it, and the leaderboard shows it. Values are
Python literals (``True``, ``0.5``, ``'covering'``). The canonical name lists
the parameters in the order of the estimator's ``__init__``, so two spellings
of one variant share their results.
"""

from __future__ import annotations

import ast
import re

from kkl_bench.estimator import Estimator
from kkl_bench.registry import did_you_mean, estimators

_NAME = re.compile(r"^(?P<base>[^\[\]]+)(\[(?P<params>.*)\])?$")


class VariantError(ValueError):
    """A variant name is malformed or names a hyperparameter the estimator does not have."""


def parse(name: str) -> tuple[str, dict]:
    """``"static_hyperkkl[guard=True]"`` -> ``("static_hyperkkl", {"guard": True})``.

    The base name is looked up in the estimator registry (unknown names raise
    its error listing the valid ones); parameters are checked against the
    estimator's ``__init__``.
    """
    base = base_name(name)
    cls = estimators.get(base)
    match = _NAME.match(name.strip())
    params = {}
    text = match["params"]
    if text is not None and text.strip():
        for item in text.split(","):
            key, equals, value = (part.strip() for part in item.partition("="))
            if not equals or not key:
                raise VariantError(
                    f"malformed parameter {item.strip()!r} in {name!r}; expected key=value"
                )
            try:
                params[key] = ast.literal_eval(value)
            except (ValueError, SyntaxError):
                raise VariantError(
                    f"value {value!r} of {key!r} in {name!r} is not a Python literal "
                    "(write True, 0.5, 'text')"
                ) from None
    valid = cls.param_names()
    unknown = [key for key in params if key not in valid]
    if unknown:
        raise VariantError(
            f"{base} has no hyperparameter {', '.join(map(repr, unknown))}; "
            f"valid: {', '.join(valid) or 'none'}{did_you_mean(unknown[0], valid)}"
        )
    return base, params


def canonical(name: str) -> str:
    """The canonical spelling of ``name``: parameters in ``__init__`` order, none if empty
    (a row suffix, ``+logged`` or ``+truth``, is kept)."""
    name, suffix = split_row(name.strip())
    base, params = parse(name)
    order = estimators.get(base).param_names()
    if not params:
        return base + suffix
    items = ",".join(f"{key}={params[key]!r}" for key in order if key in params)
    return f"{base}[{items}]{suffix}"


def build(name: str) -> Estimator:
    """An unfitted estimator for ``name`` (a registered name or a variant of one)."""
    base, params = parse(name)
    return estimators.get(base)(**params)


LOGGED = "+logged"
"""Suffix of the row of an estimator's fits that also received a true plant's logged data."""


def logged_row(name: str) -> str:
    """The row name of ``name``'s fits with logged data: ``gru_observer+logged``."""
    return f"{name}{LOGGED}"


def split_logged(row: str) -> tuple[str, bool]:
    """``"gru_observer+logged"`` -> ``("gru_observer", True)``; other rows -> ``(row, False)``."""
    if row.endswith(LOGGED):
        return row[: -len(LOGGED)], True
    return row, False


TRUTH = "+truth"
"""Suffix of the row of a Bayes-limit estimator's fits given each task's truth (its noise,
measurement model and initial box) on a track that tests generalization."""


def truth_row(name: str) -> str:
    """The row name of ``name``'s fits with the task's truth: ``particle_filter+truth``."""
    return f"{name}{TRUTH}"


def split_row(row: str) -> tuple[str, str]:
    """A row name's estimator and suffix: ``"ukf+logged"`` -> ``("ukf", "+logged")``,
    ``"ukf"`` -> ``("ukf", "")``."""
    for suffix in (LOGGED, TRUTH):
        if row.endswith(suffix):
            return row[: -len(suffix)], suffix
    return row, ""


def base_name(name: str) -> str:
    """The estimator a (variant, ``+logged`` or ``+truth``) row name refers to, read from the
    name alone (it need not be installed: stored results outlive their plugins)."""
    match = _NAME.match(split_row(name.strip())[0])
    if match is None:
        raise VariantError(
            f"malformed estimator name {name!r}; expected NAME or NAME[key=value,...]"
        )
    return match["base"].strip()
