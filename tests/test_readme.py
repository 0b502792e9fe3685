"""The README's plugin example runs, passes the conformance kit and scores a cell."""

import dataclasses
import inspect
import re
from pathlib import Path

from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.harness import RunSpec, run
from kkl_bench.measurement import MeasurementModel, NoiseLaw
from kkl_bench.protocol.system import System
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


def documented(cls) -> dict[str, str]:
    """Name -> description of everything a plugin author uses of ``cls``, from its
    docstrings: the ``Attributes`` section of the class (``a, b: text`` names two), the
    first paragraph of each public property's and method's own docstring; reStructuredText
    literals and roles as Markdown code."""
    texts = {}
    section = inspect.getdoc(cls).partition("Attributes\n----------\n")[2]
    for entry in re.split(r"\n(?=\S)", section.strip()):
        names, _, text = entry.partition(": ")
        texts.update(dict.fromkeys(names.split(", "), text))
    for name, member in vars(cls).items():
        function = member.fget if isinstance(member, property) else member
        if not name.startswith("_") and callable(function) and function.__doc__:
            texts[name] = inspect.getdoc(function).split("\n\n")[0]
    return {
        name: re.sub(r":\w+:`", "`", " ".join(text.split()).replace("``", "`"))
        for name, text in texts.items()
    }


INTERFACE = {
    "FitContext": FitContext,
    "Estimator": Estimator,
    "System": System,
    "MeasurementModel": MeasurementModel,
    "NoiseLaw": NoiseLaw,
}


def reference_table(cls) -> str:
    """The README's table for ``cls``, as :func:`documented` gives it."""
    rows = [f"| `{name}` | {text} |" for name, text in documented(cls).items()]
    return "\n".join(["| name | meaning |", "|---|---|", *rows])


def test_the_plugin_guide_names_every_field_as_its_docstring_says():
    text = README.read_text()
    for title, cls in INTERFACE.items():
        match = re.search(rf"<!-- interface:{title} -->\n(.*?)\n\n", text, re.DOTALL)
        assert match, f"README has no table after <!-- interface:{title} -->"
        assert match.group(1) == reference_table(cls), f"README's {title} table is stale"
    fields = {field.name for field in dataclasses.fields(FitContext)}
    assert fields | {"x0_low", "x0_high"} == set(documented(FitContext))
    assert {"sigma_w", "sigma_v", "logged_data"} <= fields
    assert {"uses_seed", "uses_logged_data", "fit", "estimate"} <= set(documented(Estimator))
    assert {"f", "h", "f_jacobian", "h_jacobian", "g", "n_x", "n_y"} <= set(documented(System))
    needed = {"variance", "inlier_variance", "mixture", "log_density", "observe_every", "sensor"}
    assert needed <= set(documented(MeasurementModel))
