"""What kind of estimator a row is: ``model-based``, ``learned`` or ``limit``.

Every table, CSV and page that speaks of "learned" rows or of "filters" reads a row's
family from here, never from its name or its fit time:

* ``model-based``: uses the model and trains nothing beyond choosing its free settings
  on validation streams (the EKF, UKF, EnKF);
* ``learned``: trains on data (the KKL observers, the recurrent networks);
* ``limit``: approximates the exact posterior mean, the Bayes limit of a task whose
  model it is given (the particle filter).

An estimator declares its family in the class attribute ``family``. One that declares
none reads as :data:`UNDECLARED` (``learned``: a row that does not say otherwise is a
contender against the filters), and ``kkl-bench list`` marks it as undeclared. A
``+logged`` row of a limit estimator is ``model-based``: it runs a model calibrated on
logged data, which is no task's truth.
"""

from __future__ import annotations

import pandas as pd

from kkl_bench import variants
from kkl_bench.registry import estimators

FAMILIES = ("model-based", "learned", "limit")
"""The families an estimator may declare."""
UNDECLARED = "learned"
"""The family of an estimator that declares none."""


def declared_family(cls: type) -> str | None:
    """The family ``cls`` declares, or None; ``ValueError`` naming the value and the valid
    families if it declares another."""
    family = getattr(cls, "family", None)
    if family is not None and family not in FAMILIES:
        raise ValueError(
            f"{cls.__name__} declares family={family!r}; valid families: {', '.join(FAMILIES)}"
        )
    return family


def estimator_family(cls: type) -> str:
    """The family of estimator class ``cls`` (:data:`UNDECLARED` if it declares none)."""
    return declared_family(cls) or UNDECLARED


def row_family(row: str, recorded: str = "") -> str:
    """The family of results row ``row`` (a name, variant, ``+logged`` or ``+truth`` row):
    ``recorded`` (what its cells stored) if given, else its installed estimator's; a row
    whose estimator is not installed here and recorded none reads as :data:`UNDECLARED`."""
    if recorded:
        return recorded
    name, suffix = variants.split_row(row)
    base = variants.base_name(name)
    family = estimator_family(estimators.get(base)) if base in estimators.names() else UNDECLARED
    if family == "limit" and suffix == variants.LOGGED:
        return "model-based"
    return family


def of_rows(frame: pd.DataFrame) -> pd.Series:
    """Each row's family: ``frame``'s ``family`` column, or, in a frame without one, what
    :func:`row_family` reads from the installed estimators (of its ``estimator`` column)."""
    if "family" in frame:
        return frame["family"]
    return frame["estimator"].map(row_family)


LIMIT_LABEL = "limit"
"""What a ``limit`` row's name is followed by wherever a table or figure shows it."""


def shown_name(row: str, family: str) -> str:
    """How tables and figures show results row ``row`` of ``family``: its name, followed by
    ``(limit)`` for the Bayes limit, so that no reader takes it for a contender."""
    return f"{row} ({LIMIT_LABEL})" if family == "limit" else row


def shown_names(frame: pd.DataFrame) -> dict[str, str]:
    """Each results row of ``frame`` (its ``estimator`` column) -> :func:`shown_name`."""
    families = of_rows(frame)
    return {
        row: shown_name(row, family)
        for row, family in zip(frame["estimator"], families, strict=True)
    }
