"""Whether a fit's trainings converged, read from its fit report (protocol section 6.5).

Every training of a learned row records a validation curve and whether it
converged (:func:`converged`) under a ``"converged"`` key
somewhere in its fit report: the sequence networks' training log, Phase 1's
decoder (``phase1_log``), ``injection_kkl``'s adaptation, each curriculum level,
the hypernetworks' second phase. A fit converged when all of them did.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

YES, NO, UNRECORDED, UNTRAINED = "yes", "no", "not recorded", ""
"""What the board writes for a row: every training converged, one did not, a training
without a curve (cached before curves were recorded), nothing trained (a filter)."""


CONVERGENCE_TOLERANCE = 0.05
"""A training has converged when the second half of its steps lowered the validation
error by less than this fraction of the best error of the first half (:func:`converged`)."""


DIVERGED_RATIO = 2.0
"""A training whose last validation error is above this many times its best did not
converge (:func:`converged`)."""


def converged(curve: list[tuple[int, float]] | list[list[float]]) -> bool | None:
    """Whether the training behind a validation ``curve`` (``(step, error)`` pairs in
    step order) had converged: its last error is no more than :data:`CONVERGENCE_TOLERANCE`
    below the best error of the first half of its steps. The second half, not the last
    quarter: under the cosine schedule the last quarter gets 2.5 % of the learning rate's
    integral and looks flat whether or not the budget ran out; the second half gets 18 %.
    An error that rose a little again counts as converged (more steps would not lower
    it); one that ended more than :data:`DIVERGED_RATIO` times its best, or not finite,
    did not converge: the training left its best state (a filter driven to its clip
    bounds ends flat, but far above where it started). None for a curve of fewer than
    three points, which cannot say."""
    if len(curve) < 3:
        return None
    last_step, last = curve[-1]
    errors = [error for _, error in curve]
    first_half = [error for step, error in curve if step <= 0.5 * last_step]
    if not all(math.isfinite(error) for error in errors) or last > DIVERGED_RATIO * min(errors):
        return False
    return last >= (1.0 - CONVERGENCE_TOLERANCE) * min(first_half)


def flags(report: Any) -> list[bool | None]:
    """Whether each training in a fit ``report`` (nested dicts) converged, in order: its
    ``validation_curve`` read by today's :func:`converged`, else its stored ``"converged"``."""
    if not isinstance(report, dict):
        return []
    if "validation_curve" in report:
        found = [converged(report["validation_curve"])]
    else:
        found = [report["converged"]] if "converged" in report else []
    for value in report.values():
        found += flags(value)
    return found


def curves(report: Any, path: tuple[str, ...] = ()) -> list[tuple[str, list]]:
    """Every validation curve in a fit ``report`` (nested dicts), in order, each with the
    path of keys that leads to it (``"training_log"``, ``"phase1_log.decoder"``)."""
    if not isinstance(report, dict):
        return []
    found = [(".".join(path), report["validation_curve"])] if "validation_curve" in report else []
    for key, value in report.items():
        found += curves(value, (*path, key))
    return found


def trained(report: Any) -> bool:
    """Whether the fit behind ``report`` took optimizer steps (its ``spent`` says so)."""
    spent = report.get("spent") if isinstance(report, dict) else None
    return bool(spent) and any(phase.get("steps", 0) for phase in spent.values())


def verdict(reports: Iterable[Any]) -> str:
    """:data:`NO` if any training of the fits behind ``reports`` did not converge, else
    :data:`UNRECORDED` if a fit that trained recorded no verdict (or a curve too short to
    give one), :data:`YES` if every training converged, :data:`UNTRAINED` if none trained."""
    reports = [report for report in reports if trained(report)]
    if not reports:
        return UNTRAINED
    found = [flags(report) for report in reports]
    if any(flag is False for flag_list in found for flag in flag_list):
        return NO
    if any(not flag_list or None in flag_list for flag_list in found):
        return UNRECORDED
    return YES


def worst(verdicts: Iterable[str]) -> str:
    """The verdict of several fits' verdicts (e.g. one row's over a system's tasks)."""
    present = set(verdicts)
    for candidate in (NO, UNRECORDED, YES):
        if candidate in present:
            return candidate
    return UNTRAINED
