"""The devices ``--device`` names, without torch: the command line's parsers and the run
specification check a name before anything is imported to train
(:func:`kkl_bench.support.devices.resolve` says which one ``auto`` is on this machine)."""

from __future__ import annotations

DEVICES = ("auto", "cpu", "cuda")
"""What ``--device`` accepts; ``auto`` is ``cuda`` when torch sees a GPU, else ``cpu``."""


def check_device(name: str) -> str:
    """``name`` if it is one of :data:`DEVICES` (else ``ValueError`` listing them)."""
    if name not in DEVICES:
        raise ValueError(f"unknown device {name!r}; valid devices: {', '.join(DEVICES)}")
    return name
