"""Content-keyed checkpoint cache for trained models.

A checkpoint's key is the SHA-256 of a JSON document holding everything that
determines the model (estimator configuration, system and its parameters,
protocol, seed, budget). A later run with the same key loads it; any change
makes a new key, so the model is retrained. Files are written to a
temporary name and renamed, so an interrupted save never leaves a partial
checkpoint behind. Each checkpoint has a SHA-256 sidecar (``<key>.pt.sha256``)
written after it; a checkpoint whose bytes do not match (truncated,
corrupted, or missing its sidecar) is deleted and rebuilt, never loaded.

Training a checkpoint is *claimed* (:meth:`CheckpointCache.claim`): a file
lock beside it, so concurrent workers or runs sharing a cache train each
model once; the others wait for it and load it.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock

from kkl_bench.support.cache import checksum_path, sha256_of, write_atomically


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

    @contextmanager
    def claim(self, kind: str, description: dict[str, Any]) -> Iterator[None]:
        """Hold the lock of ``description``'s checkpoint: load, or train and save, inside.

        Other processes claiming the same checkpoint wait until the block ends.
        """
        path = self.path(kind, description)
        path.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(path.with_name(path.name + ".lock")):
            yield

    def load(self, kind: str, description: dict[str, Any]) -> dict[str, Any] | None:
        """The stored checkpoint for ``description``, or None (also for a damaged one, which is removed)."""
        path = self.path(kind, description)
        if not path.exists():
            return None
        checksum = checksum_path(path)
        if checksum.exists() and checksum.read_text().strip() == sha256_of(path):
            try:
                return torch.load(path, map_location="cpu", weights_only=True)
            except Exception as error:  # damaged in a way the checksum cannot see
                reason = f"unreadable ({error})"
        else:
            reason = "checksum mismatch" if checksum.exists() else "no checksum"
        warnings.warn(
            f"discarding damaged checkpoint {path}: {reason}; it will be rebuilt", stacklevel=2
        )
        path.unlink(missing_ok=True)
        checksum.unlink(missing_ok=True)
        return None

    def remove(self, kind: str, description: dict[str, Any]) -> None:
        """Delete ``description``'s checkpoint and its checksum, if present."""
        path = self.path(kind, description)
        path.unlink(missing_ok=True)
        checksum_path(path).unlink(missing_ok=True)

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
        write_atomically(checksum_path(path), sha256_of(path))
        return path
