"""Randomness of the Monte Carlo filters (``particle_filter``, ``enkf``): one generator per
trajectory, so estimates are causal, independent of the batch and reproducible."""

from __future__ import annotations

import zlib

import numpy as np


def trajectory_generators(seed: int, first: np.ndarray) -> list[np.random.Generator]:
    """One generator per trajectory, keyed by the run's ``seed`` and the trajectory's first
    measurement (``first: (batch, n_y)``)."""
    return [
        np.random.default_rng([seed, zlib.crc32(np.ascontiguousarray(y0).tobytes())])
        for y0 in first
    ]
