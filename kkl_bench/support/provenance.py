"""Where a result's code came from: the package versions, the git commit of the checkout
(``-dirty`` if modified), Python, the platform and the time of writing."""

from __future__ import annotations

import platform
import subprocess
from datetime import UTC, datetime
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

_PACKAGES = ("kkl-bench", "numpy", "scipy", "filterpy", "pandas", "torch")


def provenance() -> dict[str, Any]:
    """Package versions, git commit, Python, platform and the time of writing."""
    return {**_static_provenance(), "written_at": datetime.now(UTC).isoformat(timespec="seconds")}


@cache
def _static_provenance() -> dict[str, Any]:
    versions = {}
    for package in _PACKAGES:
        try:
            versions[package] = version(package)
        except PackageNotFoundError:
            continue
    return {
        "versions": versions,
        "git_commit": _git_commit(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }


PACKAGE = Path(__file__).resolve().parents[1]
PUBLISHED = "leaderboard"
"""The checkout's folder of published results: runs write there, so a change in it does not
make the code dirty (:func:`_git_commit`)."""


def is_clean_commit(commit: str | None) -> bool:
    """Whether ``commit`` (a provenance's ``git_commit``) names a commit that holds the code
    as it ran: not None (outside a git checkout) and not ``-dirty``."""
    return commit is not None and not commit.endswith("-dirty")


def _git_commit(source: Path = PACKAGE) -> str | None:
    """The commit of the checkout holding ``source`` (this package), with ``-dirty`` if a
    tracked file outside :data:`PUBLISHED` is modified; None outside a git checkout."""
    try:
        commit = _git(source, "describe", "--always", "--abbrev=12")
        changed = _git(
            source,
            *("status", "--porcelain", "--untracked-files=no", "--"),
            *(":(top)", f":(top,exclude){PUBLISHED}"),
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if not commit:
        return None
    return commit + ("-dirty" if changed else "")


def _git(folder: Path, *arguments: str) -> str:
    """The stripped output of ``git arguments`` run in ``folder``."""
    return subprocess.run(
        ["git", *arguments], cwd=folder, capture_output=True, text=True, timeout=10, check=True
    ).stdout.strip()


# JSON has no inf/nan: they are stored as the strings "inf", "-inf", "nan".
