"""The HyperKKL paper's three findings, re-tested on stored results.

The paper (section "Results") draws three conclusions from its tables:

1. input-conditioned (hypernetwork) observers reduce the error of the
   autonomous KKL observer on the oscillators and Rossler under forcing;
2. curriculum learning degrades the autonomous observer, on every system and
   input;
3. on Lorenz the autonomous observer is the best of the four.

Each is written here as claims "``lower`` has a lower RMSE than ``higher``"
on a set of cells, and each claim is tested cell by cell with the paired
hierarchical bootstrap of :func:`kkl_bench.analysis.significance.compare` (one-sided,
5 %) on the cells' per-trajectory RMSE over all seeds. A cell *supports* the
claim when ``lower`` is lower at 5 %, *contradicts* it when ``higher`` is,
and is *undecided* otherwise (including cells with a diverged trajectory).
The zero input is left out of the hypernetwork claims: there the
hypernetworks equal the autonomous observer by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from kkl_bench.analysis.comparisons import comparison_frame

OSCILLATORS_AND_ROSSLER = ("duffing", "vdp", "rossler")
PAPER_SYSTEMS = (*OSCILLATORS_AND_ROSSLER, "lorenz")
FORCED = ("constant", "sinusoid", "square")
VERDICTS = {"a lower": "supports", "b lower": "contradicts"}
"""What a :func:`~kkl_bench.analysis.significance.compare` verdict of ``lower`` vs ``higher`` says
of a claim; every other verdict leaves the cell undecided."""


@dataclass(frozen=True)
class Claim:
    """``lower`` has a lower RMSE than ``higher`` on each of ``systems`` x ``regimes``."""

    lower: str
    higher: str
    systems: tuple[str, ...]
    regimes: tuple[str, ...]


@dataclass(frozen=True)
class Finding:
    title: str
    paper: str
    """What the paper says, in its words (section "Results")."""
    claims: tuple[Claim, ...]


FINDINGS = (
    Finding(
        "Input-conditioned HyperKKL helps on the oscillators and Rossler",
        "hypernetwork based observers substantially reduce estimation error on oscillatory "
        "and mildly chaotic systems under time varying forcing",
        tuple(
            Claim(hyper, "autonomous_kkl", OSCILLATORS_AND_ROSSLER, FORCED)
            for hyper in ("dynamic_hyperkkl", "static_hyperkkl")
        ),
    ),
    Finding(
        "Curriculum learning degrades",
        "Curriculum Learning performs dramatically worse than even the naive Autonomous "
        "baseline on every system and input condition tested",
        (Claim("autonomous_kkl", "curriculum_kkl", PAPER_SYSTEMS, ("zero", *FORCED)),),
    ),
    Finding(
        "On Lorenz the autonomous observer is best",
        "on the highly sensitive Lorenz attractor, the Autonomous observer remains strongest",
        tuple(
            Claim("autonomous_kkl", other, ("lorenz",), FORCED)
            for other in ("dynamic_hyperkkl", "static_hyperkkl", "curriculum_kkl")
        ),
    ),
)


def _cells(summary: pd.DataFrame, claim: Claim) -> pd.DataFrame:
    return summary[summary["system"].isin(claim.systems) & summary["regime"].isin(claim.regimes)]


def testable(summary: pd.DataFrame, claim: Claim) -> bool:
    """Whether both of the claim's estimators have results on some of its cells."""
    return {claim.lower, claim.higher} <= set(_cells(summary, claim)["estimator"])


def claim_frame(summary: pd.DataFrame, claim: Claim) -> pd.DataFrame:
    """:func:`~kkl_bench.analysis.leaderboard.comparison_frame` of ``claim.lower`` over ``claim.higher``
    on the claim's cells, with ``outcome``: supports, contradicts or undecided."""
    frame = comparison_frame(_cells(summary, claim), claim.lower, claim.higher)
    return frame.assign(outcome=[VERDICTS.get(v, "undecided") for v in frame["verdict"]])


def tally(frame: pd.DataFrame) -> str:
    """``"supports in k of n cells, contradicts in m, undecided in r"``."""
    counts = frame["outcome"].value_counts()
    return (
        f"supports in {counts.get('supports', 0)} of {len(frame)} cells, "
        f"contradicts in {counts.get('contradicts', 0)}, "
        f"undecided in {counts.get('undecided', 0)}"
    )


def tested(
    summary: pd.DataFrame,
) -> list[tuple[int, Finding, list[tuple[Claim, pd.DataFrame]]]]:
    """Each finding with a claim ``summary`` can test: its index in :data:`FINDINGS`, the
    finding, and each testable claim with its :func:`claim_frame`."""
    found = []
    for index, finding in enumerate(FINDINGS):
        claims = [claim for claim in finding.claims if testable(summary, claim)]
        if claims:
            found.append((index, finding, [(c, claim_frame(summary, c)) for c in claims]))
    return found
