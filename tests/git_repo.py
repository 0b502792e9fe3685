"""Git in a test's temporary folder."""

import subprocess
from pathlib import Path

IDENTITY = ("-c", "user.name=t", "-c", "user.email=t@t")
"""An author for commits made where git has none configured."""


def git(*arguments: str, cwd: Path) -> None:
    """Run ``git arguments`` in ``cwd``; a failure fails the test with git's output."""
    done = subprocess.run(["git", *arguments], cwd=cwd, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def commit_all(folder: Path, message: str) -> None:
    """Make ``folder`` a repository whose one commit holds everything in it."""
    git("init", "-q", cwd=folder)
    git("add", ".", cwd=folder)
    git(*IDENTITY, "commit", "-qm", message, cwd=folder)
