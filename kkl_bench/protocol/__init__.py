"""Protocol v1: system models, input signals, simulation, random streams, metrics.

Everything here is fixed by the protocol document (``docs/protocol.md``) and
depends on numpy only. The constants below are the protocol's time grid and
noise levels.

Layer: the bottom; it imports nothing else of kkl_bench.
"""

PROTOCOL_VERSION = 1
ERRATA = ("E1",)
"""Amendments to protocol v1 this implementation applies (see ``docs/protocol.md``)."""
PROTOCOL_ID = "v1+" + "+".join(ERRATA)
"""What results record as their protocol: ``"v1+E1"``."""

DT = 0.05
"""Sampling step (s)."""
N_SAMPLES = 1001
"""Samples per trajectory, ``t_k = k DT`` for k = 0..1000 (horizon 50 s)."""
SIGMA_W = 0.01
"""Standard deviation of the process noise added to every state after each step."""
SIGMA_V = 0.01
"""Standard deviation of the measurement noise added to every output sample."""
TRANSIENT_FRACTION = 0.05
"""Leading fraction of the samples left out of every metric."""
