"""Whether a fit's trainings converged, read from its fit report (protocol section 6.5).

Every training of a learned row records a validation curve and whether it
converged (:func:`kkl_bench.kkl.optimize.converged`) under a ``"converged"`` key
somewhere in its fit report: the sequence networks' training log, Phase 1's
decoder (``phase1_log``), ``injection_kkl``'s adaptation, each curriculum level,
the hypernetworks' second phase. A fit converged when all of them did.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

YES, NO, UNRECORDED, UNTRAINED = "yes", "no", "not recorded", ""
"""What the board writes for a row: every training converged, one did not, a training
without a curve (cached before curves were recorded), nothing trained (a filter)."""


def flags(report: Any) -> list[bool | None]:
    """Every ``"converged"`` value in a fit ``report`` (nested dicts), in order."""
    if not isinstance(report, dict):
        return []
    found = [report["converged"]] if "converged" in report else []
    for value in report.values():
        found += flags(value)
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
