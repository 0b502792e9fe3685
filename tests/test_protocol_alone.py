"""The protocol stands alone: numbers the suite publishes, re-derived here from the procedure
``docs/protocol.md`` states, in code written for this test (numpy, hashlib and zlib only;
nothing of kkl_bench computes them). Where the suite is consulted, it is only as the
thing the re-derivation must agree with."""

from __future__ import annotations

import hashlib
import json
import zlib

import numpy as np
import pytest

from tests.repository import BOARD_CELLS

# docs/protocol.md section 7.5: the plant table, as published
PLANT_TABLE = {
    ("lorenz", "params10"): {"p": 1.1, "q": 0.9, "r": 0.9},
    ("lorenz", "params25"): {"p": 0.75, "q": 0.75, "r": 1.25},
    ("rossler", "params10"): {"a": 1.1, "b": 0.9, "c": 1.1},
    ("duffing", "params25"): {"a": 1.25},
}
PARAMETERS = {
    "duffing": ["a"],
    "vdp": ["mu"],
    "rossler": ["a", "b", "c"],
    "lorenz": ["p", "q", "r"],
}
LEVELS = {"params10": 0.1, "params25": 0.25}


def plant_factors(system: str, plant: str) -> dict[str, float]:
    """Section 7.5: every parameter times ``1 + s level``, the signs drawn in one call."""
    level = LEVELS[plant]
    key = f"plant-p{level:g}-g1-o0"
    root = zlib.crc32(f"kkl-bench/v1/mismatch/{system}/{key}/plant".encode())
    names = PARAMETERS[system]
    signs = np.random.default_rng(root).choice((-1.0, 1.0), size=len(names))
    return {name: 1.0 + level * sign for name, sign in zip(names, signs, strict=True)}


@pytest.mark.parametrize(("system", "plant"), list(PLANT_TABLE))
def test_a_mismatch_plant_is_derived_from_the_protocol_alone(system, plant):
    from kkl_bench.suite.plants import parameter_factors  # what the suite draws
    from kkl_bench.suite.tracks import get_track

    derived = plant_factors(system, plant)
    assert derived == pytest.approx(PLANT_TABLE[system, plant])
    suite_plant = get_track("mismatch").task(f"{plant}-sinusoid").plant
    assert parameter_factors(system, suite_plant, "mismatch") == pytest.approx(derived)


def fingerprint(*arrays: np.ndarray) -> str:
    """Section 4: the first 16 hex digits of one SHA-256 over the arrays' float64 bytes."""
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


def duffing_sinusoid(n: int):
    """Sections 1-4: the first ``n`` trajectories of the paper's Duffing / sinusoid test set."""
    steps, dt, sigma = 1001, 0.05, 0.01
    root = zlib.crc32(b"kkl-bench/v1/duffing/sinusoid/test")
    x0, r, w, v = [], [], [], []
    for i in range(n):
        rng = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(i,)))
        x0.append(rng.uniform(np.array([-1.0, -1.0]), np.array([1.0, 1.0]), 2))
        r.append(rng.random(3))
        w.append(sigma * rng.standard_normal((steps - 1, 2)))
        v.append(sigma * rng.standard_normal(steps))
    x0, r, w, v = map(np.array, (x0, r, w, v))
    t = dt * np.arange(steps)
    amplitude, omega, phase = 0.5 + 0.5 * r[:, :1], 0.5 + 1.5 * r[:, 1:2], 2.0 * np.pi * r[:, 2:]
    u = amplitude * np.sin(omega * t + phase)

    def field(x, u_k):  # f(x) + g u with a = 1, g = (0, 1)
        x1, x2 = x[:, 0], x[:, 1]
        return np.stack([1.0 * x2 * x2 * x2, -x1], axis=-1) + u_k[:, None] * np.array([0.0, 1.0])

    x = np.empty((n, steps, 2))
    x[:, 0] = x0
    for k in range(steps - 1):
        state, held = x[:, k], u[:, k]
        k1 = field(state, held)
        k2 = field(state + 0.5 * dt * k1, held)
        k3 = field(state + 0.5 * dt * k2, held)
        k4 = field(state + dt * k3, held)
        x[:, k + 1] = state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4) + w[:, k]
    y = x[:, :, :1] + v[:, :, None]
    return (x0, r, w, v), (t, u[..., None], x, y)


def test_a_test_set_and_its_fingerprints_are_derived_from_the_protocol_alone():
    draws, data = duffing_sinusoid(20)
    stored = json.loads((BOARD_CELLS / "ekf" / "duffing" / "sinusoid-seed0.json").read_text())
    assert stored["n_test"] == 20
    assert fingerprint(*draws) == stored["stream_fingerprint"]
    assert fingerprint(*data) == stored["test_set_fingerprint"]
