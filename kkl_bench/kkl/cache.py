"""Content-keyed checkpoint cache for trained models.

A checkpoint's key is the SHA-256 of a JSON document holding everything that
determines the model (estimator configuration, system and its parameters,
protocol, seed, budget). A later run with the same key loads it; any change
makes a new key, so the model is retrained. Files are written to a
temporary name and renamed, so an interrupted save never leaves a partial
checkpoint behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch


def cache_key(description: dict[str, Any]) -> str:
    """First 20 hex digits of the SHA-256 of ``description`` as canonical JSON."""
    text = json.dumps(description, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class CheckpointCache:
    """Checkpoints under ``root / kind / <key>.pt``."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def path(self, kind: str, description: dict[str, Any]) -> Path:
        return self.root / kind / f"{cache_key(description)}.pt"

    def load(self, kind: str, description: dict[str, Any]) -> dict[str, Any] | None:
        """The stored checkpoint for ``description``, or None."""
        path = self.path(kind, description)
        if not path.exists():
            return None
        return torch.load(path, map_location="cpu", weights_only=True)

    def save(self, kind: str, description: dict[str, Any], state: dict[str, Any]) -> Path:
        """Store ``state`` (tensors, numbers, strings, lists, dicts) atomically."""
        path = self.path(kind, description)
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        os.close(handle)
        try:
            torch.save(
                {**state, "description": json.dumps(description, sort_keys=True, default=str)},
                temporary,
            )
            os.replace(temporary, path)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise
        return path
