"""Whether a fit's trainings converged, read from its fit report (protocol section 6.5).

Every training of a learned row records a validation curve and why it stopped
(``"stopped"``, :data:`STOPPED_BY`: the plateau rule of :mod:`kkl_bench.kkl.plateau`)
somewhere in its fit report: the sequence networks' training log, Phase 1's
encoder and decoder (``phase1_log``), each round of ``injection_kkl``'s adaptation,
each curriculum level, the hypernetworks' second phase. A training converged when the
plateau stopped it; a fit converged when all of its trainings did. Fit reports written
before the plateau rule carry no ``"stopped"``: their curves are read by the rule of
that time (:func:`outcome`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

YES, NO, DIVERGED, UNRECORDED, UNTRAINED = "yes", "no", "diverged", "not recorded", ""
"""What the board writes for a row: every training converged; one did not (its curve was
still falling); one diverged (:func:`diverged`); a training without a curve (cached before
curves were recorded); nothing trained (a filter)."""

CONVERGENCE_TOLERANCE = 0.05
"""A training has converged when the second half of its steps lowered the validation
error by less than this fraction of the best error of the first half (:func:`converged`)."""

STOPPED_BY = {"plateau": YES, "cap": NO, "diverged": DIVERGED}
"""Why a training under the plateau rule stopped, and the verdict that reads: its
validation error plateaued at the lowest learning rate; it reached its cap of steps
first; its validation error was not finite."""

DIVERGED_RATIO = 2.0
"""A training whose last validation error is above this many times its best diverged
(:func:`diverged`)."""


def diverged(curve: list[tuple[int, float]] | list[list[float]]) -> bool:
    """Whether the training behind a validation ``curve`` (``(step, error)`` pairs) left
    its best state for good: an error that is not finite, or a last error more than
    :data:`DIVERGED_RATIO` times the best (a filter driven to its clip bounds ends flat,
    but far above where it started). More steps do not mend such a training."""
    errors = [error for _, error in curve]
    if not all(math.isfinite(error) for error in errors):
        return True
    return bool(errors) and errors[-1] > DIVERGED_RATIO * min(errors)


def outcome(curve: list[tuple[int, float]] | list[list[float]]) -> str:
    """The verdict on the training behind a validation ``curve`` (``(step, error)`` pairs in
    step order): :data:`DIVERGED` (:func:`diverged`); :data:`YES` if its last error is no
    more than :data:`CONVERGENCE_TOLERANCE` below the best error of the first half of its
    steps, else :data:`NO`; :data:`UNRECORDED` for a curve of fewer than three points,
    which cannot say. The second half, not the last quarter: under the cosine schedule the
    last quarter gets 2.5 % of the learning rate's integral and looks flat whether or not
    the budget ran out; the second half gets 18 %. An error that rose a little again
    counts as converged (more steps would not lower it)."""
    if len(curve) < 3:
        return UNRECORDED
    if diverged(curve):
        return DIVERGED
    last_step, last = curve[-1]
    first_half = [error for step, error in curve if step <= 0.5 * last_step]
    return YES if last >= (1.0 - CONVERGENCE_TOLERANCE) * min(first_half) else NO


def converged(curve: list[tuple[int, float]] | list[list[float]]) -> bool | None:
    """Whether the training behind ``curve`` converged (:func:`outcome` is :data:`YES`),
    as fit reports store it; None for a curve too short to say."""
    judged = outcome(curve)
    return None if judged == UNRECORDED else judged == YES


def outcomes(report: Any) -> list[str]:
    """The verdict on each training in a fit ``report`` (nested dicts), in order: why it
    stopped (:data:`STOPPED_BY`); for a training from before the plateau rule, its
    ``validation_curve`` read by :func:`outcome`, else its stored ``"converged"`` (a
    stored False reads :data:`NO`: without the curve, divergence cannot be told)."""
    if not isinstance(report, dict):
        return []
    if report.get("stopped") in STOPPED_BY:
        found = [STOPPED_BY[report["stopped"]]]
    elif "validation_curve" in report:
        found = [outcome(report["validation_curve"])]
    elif "converged" in report:
        found = [{True: YES, False: NO}.get(report["converged"], UNRECORDED)]
    else:
        found = []
    for value in report.values():
        found += outcomes(value)
    return found


def reached_cap(report: Any) -> bool:
    """Whether a training in the fit ``report`` (nested dicts) reached its cap of steps
    before the plateau rule stopped it (``"stopped": "cap"``): the fits that a higher cap
    makes differently; one the rule stopped takes the same steps under any higher cap."""
    if not isinstance(report, dict):
        return False
    return report.get("stopped") == "cap" or any(map(reached_cap, report.values()))


def trainings(report: Any, path: tuple[str, ...] = ()) -> list[tuple[str, dict]]:
    """Every training's record in a fit ``report`` (nested dicts; a record is a dict with a
    ``validation_curve``), in order, each with the path of keys that leads to it
    (``"training_log"``, ``"phase1_log.decoder"``)."""
    if not isinstance(report, dict):
        return []
    found = [(".".join(path), report)] if "validation_curve" in report else []
    for key, value in report.items():
        found += trainings(value, (*path, key))
    return found


def curves(report: Any) -> list[tuple[str, list]]:
    """Every validation curve in a fit ``report``, in order, with its path (:func:`trainings`)."""
    return [(path, record["validation_curve"]) for path, record in trainings(report)]


def trained(report: Any) -> bool:
    """Whether the fit behind ``report`` took optimizer steps (its ``spent`` says so)."""
    spent = report.get("spent") if isinstance(report, dict) else None
    return bool(spent) and any(phase.get("steps", 0) for phase in spent.values())


def verdict(reports: Iterable[Any]) -> str:
    """The worst (:func:`worst`) verdict on the trainings of the fits behind ``reports``;
    :data:`UNRECORDED` for a fit that trained and recorded none, :data:`UNTRAINED` if
    none trained."""
    reports = [report for report in reports if trained(report)]
    if not reports:
        return UNTRAINED
    fits = [outcomes(report) or [UNRECORDED] for report in reports]
    return worst(judged for fit in fits for judged in fit)


def worst(verdicts: Iterable[str]) -> str:
    """The verdict of several verdicts (a fit's trainings, a row's cells): :data:`DIVERGED`
    over :data:`NO` over :data:`UNRECORDED` over :data:`YES`; :data:`UNTRAINED` if none."""
    present = set(verdicts)
    for candidate in (DIVERGED, NO, UNRECORDED, YES):
        if candidate in present:
            return candidate
    return UNTRAINED
