"""The package's layers hold: `pyproject.toml`'s import-linter contracts pass, and an
upward import breaks them."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.repository import REPOSITORY

PLUGIN_FOLDERS = ("estimators", "systems", "tasks")
"""Installed inside the package (pyproject's package-dir), kept at the top of the repository."""


def assembled(folder: Path) -> Path:
    """The package laid out as it installs (the plugin folders inside it), with the
    configuration beside it: import-linter reads the tree from the file system."""
    shutil.copytree(REPOSITORY / "kkl_bench", folder / "kkl_bench")
    for name in PLUGIN_FOLDERS:
        shutil.copytree(REPOSITORY / name, folder / "kkl_bench" / name)
    shutil.copy(REPOSITORY / "pyproject.toml", folder)
    return folder


def lint(folder: Path) -> subprocess.CompletedProcess:
    linter = Path(sys.executable).parent / "lint-imports"
    return subprocess.run(
        [str(linter), "pyproject.toml", "--no-cache"],
        cwd=folder,
        env={"PYTHONPATH": str(folder), "PATH": str(linter.parent)},
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture
def tree(tmp_path) -> Path:
    return assembled(tmp_path)


def test_every_layer_imports_only_those_below_it(tree):
    done = lint(tree)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Contracts: 2 kept, 0 broken." in done.stdout


def test_an_upward_import_breaks_the_contract(tree):
    metrics = tree / "kkl_bench" / "protocol" / "metrics.py"
    metrics.write_text(metrics.read_text() + "\nfrom kkl_bench.report import board  # upward\n")
    done = lint(tree)
    assert done.returncode == 1
    assert "kkl_bench.protocol is not allowed to import kkl_bench.report" in " ".join(
        done.stdout.split()
    )
