"""The README's plugin examples run, pass the conformance kits and score cells."""

import dataclasses
import inspect
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from kkl_bench.cli import build_parser
from kkl_bench.estimator import Estimator, FitContext
from kkl_bench.measurement import MeasurementModel, NoiseLaw
from kkl_bench.protocol.system import System
from kkl_bench.registry import estimators
from kkl_bench.run.harness import RunSpec, run
from kkl_bench.suite.task import get_profile
from kkl_bench.testing import Conformance
from tests.repository import README
from tests.test_devices import fits_on_cpu_and_gpu


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


@pytest.mark.slow
def test_the_plugin_package_of_the_readme_installs_checks_and_runs(tmp_path):
    """The package's files copied from the README into a fresh folder, installed (into a
    folder of its own on PYTHONPATH rather than this environment, which the README's
    `pip install -e .` would change for every later test), then every other line of the
    README's commands run there as written."""
    package = tmp_path / "my-plugins"
    (package / "my_plugins").mkdir(parents=True)
    (package / "my_plugins" / "__init__.py").write_text("")
    files = re.findall(
        r"<!-- readme-plugin-file:(\S+) -->\n```\w+\n(.*?)```", README.read_text(), re.DOTALL
    )
    assert {name for name, _ in files} == {
        "my_plugins/pendulum.py", "my_plugins/window_mlp.py", "tracks/forced-pendulum.toml",
        "pyproject.toml",
    }  # fmt: skip
    for name, text in files:
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", site, package],
        check=True,
        capture_output=True,
    )
    environment = {**os.environ, "PYTHONPATH": str(site), "KKL_BENCH_CACHE": str(tmp_path)}
    commands = [
        line.split("#")[0].strip()
        for line in readme_block("readme-plugin-commands").splitlines()
        if line.strip() and not line.startswith("pip ")
    ]
    assert len(commands) == 4
    bin_dir = Path(sys.executable).parent
    for command in commands:
        words = shlex.split(command)
        assigned = dict(word.split("=", 1) for word in words if "=" in word and word[0].isupper())
        words = [word for word in words if word.split("=", 1)[0] not in assigned]
        done = subprocess.run(
            [str(bin_dir / words[0]), *words[1:]],
            cwd=package,
            env={**environment, **assigned},
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"{command}\n{done.stdout}\n{done.stderr}"
        if words[1] == "check":
            assert " 0 failed" in done.stdout, done.stdout
        else:
            assert " 0 failed; results in results/quick/" in done.stdout, done.stdout


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_readme_s_learned_plugin_trains_on_a_gpu_as_on_the_cpu():
    namespace = {"__name__": "window_mlp"}
    plugin = readme_block("readme-plugin-file:my_plugins/window_mlp.py")
    exec(compile(plugin, "README.md", "exec"), namespace)
    fits = fits_on_cpu_and_gpu(Conformance(namespace["WindowMLP"]()))
    logs = {device: fit.fit_report()["training_log"] for device, fit in fits.items()}
    assert logs["cuda"]["spent"]["device"] == "cuda"
    first = [log["validation_curve"][0][1] for log in logs.values()]
    assert first[1] == pytest.approx(first[0], rel=1e-5)  # the same weights and data


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


def documented_commands() -> list[tuple[str, str]]:
    """``(file, command)`` for each ``kkl-bench`` command in the code blocks of the README
    and of ``docs/`` (a line's commands joined by ``&&`` or ``;`` apart; a line continued
    with a backslash joined)."""
    found = []
    for path in [README, *sorted((README.parent / "docs").glob("*.md"))]:
        for block in re.findall(r"```\w*\n(.*?)```", path.read_text(), re.DOTALL):
            for line in block.replace("\\\n", " ").splitlines():
                for command in re.split(r"&&|;", line):
                    if command.strip().startswith("kkl-bench "):
                        found.append((path.name, command.strip()))
    return found


def test_every_command_in_the_documentation_s_code_blocks_parses(capsys):
    """An option renamed or removed fails here, not in a reader's terminal."""
    commands = documented_commands()
    assert len(commands) > 20
    refused = []
    for source, command in commands:
        argv = shlex.split(command.partition(" > ")[0], comments=True)[1:]
        try:
            build_parser(argv).parse_args(argv)
        except SystemExit as exit_status:
            if exit_status.code:
                refused.append(f"{source}: {command}: {capsys.readouterr().err.strip()}")
    assert not refused, "\n".join(refused)
