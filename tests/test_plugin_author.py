"""A plugin author's whole path, as the README describes it: install a plugin package, check
it, run it, time it and publish it into a copy of the committed board, which nothing of it
may damage; a smoke-profile board is refused there."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from kkl_bench.analysis.cost import COST_FILE, read_costs
from kkl_bench.report.publish import MANIFEST
from tests.repository import BOARD

pytest.importorskip("matplotlib")

PLUGIN = Path(__file__).parent / "fixtures" / "fd_ekf_plugin"
ROW = "fd_ekf"


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, str]:
    """The environment of a shell in which the plugin package is pip-installed."""
    target = tmp_path_factory.mktemp("site")
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", target, PLUGIN],
        check=True,
        capture_output=True,
    )
    path = os.pathsep.join(filter(None, [str(target), os.environ.get("PYTHONPATH")]))
    return {**os.environ, "PYTHONPATH": path}


def kkl_bench(environment: dict[str, str], *arguments, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "kkl_bench.cli", *map(str, arguments)],
        env=environment,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
    )


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` but the raw results, by relative path."""
    return {
        str(path.relative_to(folder)): path.read_bytes()
        for path in folder.rglob("*")
        if path.is_file() and "results" not in path.relative_to(folder).parts
    }


CONCERNED = {
    MANIFEST,  # the redrawn figures' digests
    "README.md",
    "index.html",
    "standard.csv",
    "standard.tex",
    COST_FILE,
    *(
        f"figures/{name}.{kind}"
        for name in ("relative-rmse", "cost-accuracy")
        for kind in ("png", "svg")
    ),
    *(
        f"figures/trajectory-duffing-{regime}.{kind}"
        for regime in ("zero", "constant", "sinusoid", "square")
        for kind in ("png", "svg")
    ),
}
"""The published files a new paper-track row on Duffing may change."""

WRITTEN_AS_TEXT = ("README.md", "index.html", "standard.csv", "standard.tex", COST_FILE)
"""Published files whose bytes are the same on every machine (a figure's are not)."""


@pytest.mark.slow  # a whole `standard` profile on Duffing and two publications of the board
@pytest.mark.skipif(not (BOARD / MANIFEST).exists(), reason="no committed board in this checkout")
def test_a_plugin_row_reaches_a_copy_of_the_board_without_harming_it(installed, tmp_path):
    listed = kkl_bench(installed, "list", cwd=tmp_path)
    assert listed.returncode == 0 and ROW in listed.stdout.split("estimators: ")[1].split("\n")[0]
    checked = kkl_bench(installed, "check", ROW, cwd=tmp_path)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "PASS lorenz check_causal" in checked.stdout

    board = tmp_path / "board"
    shutil.copytree(BOARD, board, ignore=shutil.ignore_patterns("pending"))  # not the board's

    # The copy as this machine publishes it before the plugin's row: a figure whose inputs'
    # digest the code has changed since the board was published is drawn again, and its
    # bytes repeat on one machine only (another's differed in the sixth decimal of a few
    # path coordinates), which is not the plugin's doing.
    def publish() -> subprocess.CompletedProcess:
        return kkl_bench(
            installed, "publish", "--results", "board/results", "--out", "board", cwd=tmp_path
        )

    unchanged = publish()
    assert unchanged.returncode == 0, unchanged.stderr
    before = snapshot(board)
    for name in WRITTEN_AS_TEXT:  # the committed board is what this code publishes
        assert before[name] == (BOARD / name).read_bytes(), (
            f"leaderboard/{name} is not what `kkl-bench publish --results leaderboard/results "
            "--out leaderboard` writes with this code: publish it again"
        )
    ran = kkl_bench(
        installed, "run", "--estimator", ROW, "--system", "duffing", "--profile", "standard",
        "--results", "board/results", cwd=tmp_path,
    )  # fmt: skip
    assert ran.returncode == 0, ran.stderr
    timed = kkl_bench(
        installed, "cost", "--estimator", ROW, "--system", "duffing", "--rounds", "1",
        "--out", "board", cwd=tmp_path,
    )  # fmt: skip
    assert timed.returncode == 0, timed.stderr
    costs, committed = read_costs(board / COST_FILE), read_costs(BOARD / COST_FILE)
    mine = costs["estimator"] == ROW
    assert mine.sum() == 4 and (costs.loc[mine, "reference_us_per_trajectory_step"] > 0).all()
    assert costs[~mine].reset_index(drop=True).equals(committed)  # every other row as it was

    published = publish()
    assert published.returncode == 0, published.stderr
    after = snapshot(board)
    assert set(after) == set(before)
    changed = {name for name in before if before[name] != after[name]}
    assert changed - CONCERNED == set()
    assert {"README.md", "standard.csv", COST_FILE} <= changed
    readme = (board / "README.md").read_text()
    assert f"| `{ROW}` " in readme and "kkl-bench run --estimator fd_ekf --system duffing" in readme

    # a smoke run of the plugin is refused by the board, which stays as it was
    smoke = kkl_bench(
        installed, "run", "--estimator", ROW, "--system", "duffing", "--regime", "zero",
        "--results", "smoke", cwd=tmp_path,
    )  # fmt: skip
    assert smoke.returncode == 0, smoke.stderr
    refused = kkl_bench(installed, "publish", "--results", "smoke", "--out", "board", cwd=tmp_path)
    assert refused.returncode == 2
    assert "its board is of profile 'standard' (this is 'quick')" in refused.stderr
    assert "--force" in refused.stderr
    assert snapshot(board) == after


def test_publish_into_the_committed_board_from_smoke_results_is_refused(tmp_path):
    """Straight against the repository's own folder: a refusal writes nothing."""
    if not (BOARD / MANIFEST).exists():
        pytest.skip("no committed board in this checkout")
    from kkl_bench.cli import main

    smoke = tmp_path / "smoke"
    assert main(["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero",
                 "--results", str(smoke)]) == 0  # fmt: skip
    before = snapshot(BOARD)
    assert main(["publish", "--results", str(smoke), "--out", str(BOARD)]) == 2
    assert snapshot(BOARD) == before
    assert pd.read_json(BOARD / MANIFEST, typ="series")["profile"] == "standard"
