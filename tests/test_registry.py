"""The generic registry: decorator, entry-point discovery (with metadata fakes), errors."""

import importlib.metadata
import sys
import textwrap
import warnings

import pytest

from kkl_bench import registry as registry_module
from kkl_bench.registry import (
    PluginLoadError,
    Registry,
    UnknownNameError,
    estimators,
    regimes,
    systems,
)


@pytest.fixture
def plugin_package(tmp_path, monkeypatch):
    """A throwaway importable module with one good and one broken plugin."""
    (tmp_path / "throwaway_plugin.py").write_text(
        textwrap.dedent(
            """
            class Good:
                pass
            """
        )
    )
    (tmp_path / "broken_plugin.py").write_text("raise RuntimeError('missing dependency xyz')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield
    sys.modules.pop("throwaway_plugin", None)
    sys.modules.pop("broken_plugin", None)


def fake_entry_points(*points):
    def entry_points(group):
        return [point for point in points if point.group == group]

    return entry_points


@pytest.fixture
def widgets(plugin_package, monkeypatch) -> Registry:
    """A registry of two entry-point plugins: ``good`` and ``broken`` (raises on import)."""
    group = "kkl_bench.test_kind"
    monkeypatch.setattr(
        registry_module.importlib.metadata,
        "entry_points",
        fake_entry_points(
            importlib.metadata.EntryPoint("good", "throwaway_plugin:Good", group),
            importlib.metadata.EntryPoint("broken", "broken_plugin:Thing", group),
        ),
    )
    return Registry("widget", group)


def test_entry_point_plugins_load_lazily_and_a_broken_one_spares_the_rest(widgets):
    registry = widgets
    assert registry.names() == ["broken", "good"]
    assert "throwaway_plugin" not in sys.modules  # nothing imported yet
    assert registry.get("good").__name__ == "Good"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the error says it once; no warning repeats it
        with pytest.raises(PluginLoadError, match="missing dependency xyz"):
            registry.get("broken")
    assert registry.names() == ["good"]
    assert "missing dependency xyz" in registry.failures()["broken"]
    with pytest.raises(PluginLoadError, match="failed to load"):  # reported again, not re-imported
        registry.get("broken")


def test_broken_imports_every_plugin_and_names_the_ones_that_fail(widgets):
    registry = widgets
    broken = registry.broken()
    assert list(broken) == ["broken"]
    assert "RuntimeError: missing dependency xyz" in broken["broken"]
    assert registry.names() == ["good"]


def test_decorator_registers_and_refuses_silent_replacement():
    registry = Registry("widget", "kkl_bench.nothing_here")

    @registry.register("a")
    class A:
        pass

    assert registry.get("a") is A
    registry.register("a")(A)  # the same object again is fine
    with pytest.raises(ValueError, match="already registered"):
        registry.register("a")(type("B", (), {}))


def test_unknown_name_lists_valid_names_and_suggests():
    with pytest.raises(
        UnknownNameError,
        match=r"unknown system 'lorentz'; valid systems: chua, duffing, fitzhugh_nagumo, lorenz, "
        r"lorenz96-n5, lorenz96-n10, lorenz96-n20, lorenz96-n40, lorenz96-n80, lorenz96-n160, "
        r"rossler, vdp "
        r"\(did you mean 'lorenz'\?\)",
    ):
        systems.get("lorentz")


def test_builtins_are_discovered_through_their_entry_points():
    """The built-ins are declared as entry points of the installed distribution."""
    declared = {
        point.name for point in importlib.metadata.entry_points(group="kkl_bench.estimators")
    }
    assert {
        "ekf",
        "ukf",
        "autonomous_kkl",
        "curriculum_kkl",
        "static_hyperkkl",
        "dynamic_hyperkkl",
        "injection_kkl",
    } <= declared
    assert {point.name for point in importlib.metadata.entry_points(group="kkl_bench.systems")} >= {
        "duffing",
        "vdp",
        "rossler",
        "lorenz",
    }
    assert regimes.names() == [
        "chirp",
        "constant",
        "multisine",
        "ramp",
        "random_steps",
        "sinusoid",
        "square",
        "zero",
    ]
    assert {"ekf", "ukf"} <= set(estimators.names())
