"""The README's plugin example runs, passes the conformance kit and scores a cell."""

import re
from pathlib import Path

from kkl_bench.harness import RunSpec, run
from kkl_bench.registry import estimators
from kkl_bench.task import get_profile

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_block(marker: str) -> str:
    match = re.search(rf"<!-- {marker} -->\n```\w+\n(.*?)```", README.read_text(), re.DOTALL)
    assert match, f"README has no code block after <!-- {marker} -->"
    return match.group(1)


def test_plugin_example_runs_and_scores(tmp_path, monkeypatch):
    monkeypatch.setattr(estimators, "_loaded", dict(estimators._loaded))
    exec(compile(readme_block("readme-example"), "README.md", "exec"), {})  # runs check_estimator
    spec = RunSpec(
        ("nudged_model",), ("vdp",), ("sinusoid",), get_profile("quick"), results_dir=tmp_path
    )
    summary = run(spec)
    assert summary.ok and summary.scored[0].estimator_params == {"gain": 0.5}
    assert max(summary.scored[0].rmse) < 1.0


def test_ci_runs_the_readme_test_command():
    ci_script = (README.parent / ".ci" / "run").read_text()
    assert "ci:test-command" in ci_script
    assert "pytest" in readme_block("ci:test-command")
