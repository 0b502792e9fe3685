"""Which entries of a leaderboard column are really best: a paired, hierarchical bootstrap.

Every estimator of a column is scored on the same test trajectories, once
per training seed, so its per-trajectory RMSE is an array
``(n_seeds, n_trajectories)``. The *best* entry has the lowest mean RMSE.
Another entry is *distinguishable* from it when the ratio of their mean
RMSEs, ``other / best``, exceeds 1 with 95 % confidence (one-sided, 5 %):

* each bootstrap resample draws the test trajectories with replacement,
  the same draws for both estimators (the comparison is paired), and each
  estimator's seeds with replacement (independently: the seeds of two
  estimators are unrelated), so both the test-set noise and the spread over
  training seeds enter the interval;
* the ratio's 5 % quantile over the resamples must be above 1.

The best entry is marked *best* only if it is distinguishable from every
other entry *by more than a margin of practical equivalence*: the ratio's 5 %
quantile must be above ``1 + margin`` (:data:`MARGIN`, 1 %), so that two entries
that differ by rounding, or by less than anyone would care about, are never
told apart however many trajectories agree on it. Otherwise the best entry
and every entry not distinguishable from it in that way are marked *tied*.
Entries with a diverged trajectory (non-finite RMSE) are never best and never
tied; a column with fewer than two finite entries has no marks. Resampling
uses a fixed seed, so the marks are reproducible.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import numpy as np

N_RESAMPLES = 4000
LEVEL = 0.05
SEED = 20240601
MARGIN = 0.01
"""Practical-equivalence margin of the marks: a win must be by more than 1 %."""


@functools.cache
def _draws(
    n_trajectories: int, n_seeds_other: int, n_seeds_best: int, n_resamples: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The resamples of :func:`resampled_ratios`, drawn from :data:`SEED` in its order: the
    shared trajectory indices ``(n_resamples, n_trajectories)``, then each side's seed
    indices ``(n_resamples, n_seeds)``. They depend on the shapes alone, so a column's
    comparisons draw them once (read-only arrays)."""
    rng = np.random.default_rng(SEED)
    draws = (
        rng.integers(n_trajectories, size=(n_resamples, n_trajectories)),
        rng.integers(n_seeds_other, size=(n_resamples, n_seeds_other)),
        rng.integers(n_seeds_best, size=(n_resamples, n_seeds_best)),
    )
    for draw in draws:
        draw.flags.writeable = False
    return draws


def per_seed_means(rmse: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """Each seed's mean RMSE over each resample of the trajectories ``(n_seeds, n_resamples)``.

    ``rmse: (n_seeds, n_trajectories)``; ``trajectories: (n_resamples, n_trajectories)``
    the (shared) resampled trajectory indices.
    """
    return rmse[:, trajectories].mean(axis=-1)


def resampled_means(per_seed: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Mean RMSE of each resample ``(n_resamples,)``: ``per_seed`` (:func:`per_seed_means`,
    ``(n_seeds, n_resamples)``) averaged over the resampled seed indices ``seeds: (n_resamples,
    n_seeds)``."""
    return per_seed[seeds, np.arange(len(seeds))[:, None]].mean(axis=1)


def resampled_ratios(
    other: np.ndarray,
    best: np.ndarray,
    n_resamples: int = N_RESAMPLES,
    best_per_seed: np.ndarray | None = None,
) -> np.ndarray:
    """``mean(other) / mean(best)`` over paired hierarchical resamples ``(n_resamples,)``.

    ``other: (n_seeds_a, n)`` and ``best: (n_seeds_b, n)`` per-trajectory RMSE on the
    same ``n`` test trajectories; ``best_per_seed``, if given, is ``best``'s
    :func:`per_seed_means` over these resamples (a column compares every entry with one best).
    """
    other, best = np.asarray(other, float), np.asarray(best, float)
    if other.shape[1] != best.shape[1]:
        raise ValueError(
            f"paired comparison needs the same test trajectories: {other.shape[1]} vs {best.shape[1]}"
        )
    trajectories, seeds_other, seeds_best = _draws(
        best.shape[1], other.shape[0], best.shape[0], n_resamples
    )
    if best_per_seed is None:
        best_per_seed = per_seed_means(best, trajectories)
    other_means = resampled_means(per_seed_means(other, trajectories), seeds_other)
    return other_means / resampled_means(best_per_seed, seeds_best)


def ratio_lower_bound(
    other: np.ndarray,
    best: np.ndarray,
    n_resamples: int = N_RESAMPLES,
    level: float = LEVEL,
    best_per_seed: np.ndarray | None = None,
) -> float:
    """One-sided lower confidence bound (at ``level``) of ``mean(other) / mean(best)``
    (``best_per_seed`` as in :func:`resampled_ratios`)."""
    ratios = resampled_ratios(other, best, n_resamples, best_per_seed)
    return float(np.quantile(ratios, level))


def compare(a: np.ndarray, b: np.ndarray, level: float = LEVEL) -> dict[str, float | str]:
    """``mean(a) / mean(b)`` with its two-sided ``1 - 2 level`` bootstrap interval and a verdict.

    The verdict is ``"a lower"`` when the upper bound is below 1, ``"b lower"``
    when the lower bound is above 1 (each a one-sided test at ``level``),
    else ``"not distinguishable"``; ``"diverged"`` if either has a non-finite value.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return {
            "ratio": float(a.mean() / b.mean()),
            "low": np.nan,
            "high": np.nan,
            "verdict": "diverged",
        }
    ratios = resampled_ratios(a, b)
    low, high = np.quantile(ratios, [level, 1 - level])
    verdict = "a lower" if high < 1 else "b lower" if low > 1 else "not distinguishable"
    return {
        "ratio": float(a.mean() / b.mean()),
        "low": float(low),
        "high": float(high),
        "verdict": verdict,
    }


def mark_column(rmse: Mapping[str, np.ndarray], margin: float = MARGIN) -> dict[str, str]:
    """``{"best"|"tied"|"": ...}`` for each entry of one column.

    ``rmse`` maps an entry's name to its per-trajectory RMSE ``(n_seeds, n_trajectories)``;
    an entry is told apart from the best only if the lower bound of its ratio to the best
    is above ``1 + margin``.
    """
    if not margin >= 0:
        raise ValueError(f"the practical-equivalence margin must be >= 0, got {margin!r}")
    finite = {name: np.asarray(v, float) for name, v in rmse.items() if np.isfinite(v).all()}
    marks = dict.fromkeys(rmse, "")
    if len(finite) < 2:
        return marks
    best = min(finite, key=lambda name: finite[name].mean())
    # drawn first, so the same whatever the seed counts: every comparison's trajectories
    trajectories = _draws(finite[best].shape[1], 1, 1, N_RESAMPLES)[0]
    best_per_seed = per_seed_means(finite[best], trajectories)
    tied = [
        name
        for name, values in finite.items()
        if name != best
        and ratio_lower_bound(values, finite[best], best_per_seed=best_per_seed) <= 1.0 + margin
    ]
    marks[best] = "tied" if tied else "best"
    for name in tied:
        marks[name] = "tied"
    return marks
