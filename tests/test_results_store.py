"""The results store under faults: damaged files named, moved aside and recomputed; no table
mixing protocol or toolkit versions."""

import errno
import json
import re
import subprocess

import pytest

from kkl_bench.cli import main
from kkl_bench.run.results import DamagedCellError, read_cell
from tests.test_executors import run_command

ARGS = ["--estimator", "ekf", "--system", "vdp", "--regime", "zero", "square"]


@pytest.fixture
def results(tmp_path, capsys):
    assert main(["run", *ARGS, "--results", str(tmp_path)]) == 0
    capsys.readouterr()
    return tmp_path


def cell(results, regime="zero"):
    return results / "quick" / "ekf" / "vdp" / f"{regime}-seed0.json"


def truncate(path):
    path.write_bytes(path.read_bytes()[:100])  # a partial copy


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (truncate, "not valid JSON (Unterminated string"),
        (
            lambda path: path.write_text("{}"),
            "missing fields estimator, n_test, profile, regime, seed, status",
        ),
        (lambda path: path.write_text("[1, 2]"), "expected a JSON object, found list"),
        (
            lambda path: path.write_text(
                json.dumps({**json.loads(path.read_text()), "record_format": 0})
            ),
            "record format 0, this kkl-bench reads formats 1, 2, 3; rerun the cell",
        ),
        (
            lambda path: path.write_text(json.dumps({**json.loads(path.read_text()), "colour": 1})),
            "unknown fields colour",
        ),
    ],
)
def test_a_damaged_cell_is_named_with_its_reason(results, damage, reason):
    path = cell(results)
    damage(path)
    with pytest.raises(DamagedCellError) as error:
        read_cell(path)
    assert str(path) in str(error.value) and reason in str(error.value)


def test_run_moves_a_truncated_cell_aside_and_recomputes_it(results, capsys):
    path = cell(results)
    original = json.loads(path.read_text())
    truncate(path)
    with pytest.warns(
        UserWarning,
        match=f"damaged result file {path}: not valid JSON.*moved to zero-seed0.json.corrupt",
    ):
        assert main(["run", *ARGS, "--results", str(results)]) == 0
    assert "1 cells scored, 1 already done, 0 failed" in capsys.readouterr().out
    assert read_cell(path).rmse == original["rmse"]
    assert path.with_name("zero-seed0.json.corrupt").read_bytes() != path.read_bytes()


def test_the_leaderboard_leaves_a_damaged_cell_out_names_it_and_fails_unless_tolerated(
    results, capsys
):
    path = cell(results, "square")
    path.write_text("{}")
    assert main(["leaderboard", "--results", str(results)]) == 1
    captured = capsys.readouterr()
    assert f"left out damaged result file {path}: missing fields" in captured.err
    assert "Van der Pol Zero" in captured.out and "Van der Pol Sqr" not in captured.out
    assert main(["leaderboard", "--results", str(results), "--tolerate-damaged"]) == 0
    assert "left out damaged result file" in capsys.readouterr().err


def rewrite(path, **changes):
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def test_tables_refuse_to_mix_protocol_or_toolkit_versions_unless_grouped(results, capsys):
    rewrite(cell(results, "square"), protocol="v1")
    assert main(["leaderboard", "--results", str(results)]) == 2
    error = capsys.readouterr().err
    assert "mix versions that one table must not mix" in error
    assert (
        "protocol v1, KKL toolkit None: 1 cells; protocol v1+E1, KKL toolkit None: 1 cells" in error
    )
    assert main(["leaderboard", "--results", str(results), "--by-version"]) == 0
    out = capsys.readouterr().out
    assert "protocol v1, KKL toolkit None" in out and "protocol v1+E1, KKL toolkit None" in out
    assert out.count("| Estimator") == 2

    rewrite(cell(results, "square"), protocol="v1+E1", fit_report={})
    rewrite(cell(results, "zero"), fit_report={"toolkit": 5})
    assert main(["publish", "--results", str(results), "--out", str(results / "out")]) == 0

    rewrite(cell(results, "square"), fit_report={"toolkit": 4})
    assert main(["publish", "--results", str(results), "--out", str(results / "out")]) == 2
    assert (
        "KKL toolkit 4: 1 cells; protocol v1+E1, KKL toolkit 5: 1 cells" in capsys.readouterr().err
    )


def test_two_runs_on_one_results_folder_score_each_cell_once(tmp_path):
    command = run_command(tmp_path, "--system", "duffing", "vdp", "--regime", "zero", "square")
    runs = [subprocess.Popen(command, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    counts = []
    for process in runs:
        out, _ = process.communicate(timeout=300)
        assert process.returncode == 0
        scored, done = re.search(r"(\d+) cells scored, (\d+) already done, 0 failed", out).groups()
        counts.append((int(scored), int(done)))
    assert sum(scored for scored, _ in counts) == 8  # every cell scored by exactly one run
    assert all(scored + done == 8 for scored, done in counts)
    assert len(list(tmp_path.glob("quick/*/*/*.json"))) == 8
    assert (tmp_path / ".claims" / ".gitignore").read_text() == "*\n"  # locks stay out of git


def test_a_write_that_fails_part_way_leaves_no_file_and_a_clear_error(
    tmp_path, monkeypatch, capsys
):
    from kkl_bench.run import results as store

    def full_disk(descriptor):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(store.os, "fsync", full_disk)
    assert main(["run", *ARGS, "--results", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert re.search(
        r"kkl-bench: error: \[Errno 28\] could not write \S+/vdp/zero-seed0\.(json|npz): No space",
        error,
    )
    written = [p for p in tmp_path.rglob("*") if p.is_file() and ".claims" not in p.parts]
    assert written == []  # nothing partial, no temporaries
