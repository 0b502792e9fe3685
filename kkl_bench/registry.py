"""One generic plugin registry, used for systems, input regimes and estimators.

A plugin becomes known in one of two ways, which end in the same table:

* the :meth:`Registry.register` decorator, run when the defining module is
  imported (handy in a script or notebook);
* an entry point in the registry's group (``kkl_bench.systems``,
  ``kkl_bench.regimes``, ``kkl_bench.estimators``), declared in the
  ``pyproject.toml`` of any installed distribution. Entry points are read on
  the first lookup and imported only when their name is asked for, so a
  broken plugin never stops the others from loading; asking for it raises
  :class:`PluginLoadError` with the import error, and :meth:`Registry.broken`
  names every such plugin.

The built-in plugins are declared as entry points of this distribution,
exactly as a third party declares its own.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib.metadata
import re
from collections.abc import Callable, Iterable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")


class UnknownNameError(KeyError):
    """A registry was asked for a name it does not hold."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


class PluginLoadError(ImportError):
    """An entry-point plugin failed to import."""


class Registry(Generic[T]):
    """Name -> plugin table for one kind of plugin.

    Parameters
    ----------
    kind:
        Human-readable kind, used in error messages ("estimator").
    group:
        Entry-point group scanned on first lookup ("kkl_bench.estimators").
    """

    def __init__(self, kind: str, group: str) -> None:
        self.kind = kind
        self.group = group
        self._loaded: dict[str, T] = {}
        self._lazy: dict[str, importlib.metadata.EntryPoint] = {}
        self._failed: dict[str, str] = {}
        self._scanned = False

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator registering ``obj`` under ``name``; returns ``obj`` unchanged."""

        def decorator(obj: T) -> T:
            existing = self._loaded.get(name)
            if existing is not None and existing is not obj:
                raise ValueError(
                    f"{self.kind} {name!r} is already registered as {existing!r}; "
                    f"refusing to replace it with {obj!r}"
                )
            self._loaded[name] = obj
            self._lazy.pop(name, None)
            return obj

        return decorator

    def get(self, name: str) -> T:
        """The plugin registered as ``name``, importing it if it is an entry point."""
        self._scan()
        if name in self._loaded:
            return self._loaded[name]
        if name in self._lazy:
            return self._load(name)
        if name in self._failed:
            raise PluginLoadError(f"{self.kind} {name!r} failed to load: {self._failed[name]}")
        raise UnknownNameError(self._unknown_message(name))

    def names(self) -> list[str]:
        """Names of every registered plugin, loaded or not (failed ones excluded), sorted with
        numbers by value (``lorenz96-n5`` before ``lorenz96-n10``)."""
        self._scan()
        return sorted(set(self._loaded) | set(self._lazy), key=_natural)

    def failures(self) -> dict[str, str]:
        """Entry points that failed to import: name -> reason."""
        self._scan()
        return dict(self._failed)

    def broken(self) -> dict[str, str]:
        """Import every entry point not imported yet; those that fail: name -> reason.

        For listing what is usable (``kkl-bench list``); lookups stay lazy."""
        self._scan()
        for name in list(self._lazy):
            if name in self._lazy:  # importing one module may register others
                with contextlib.suppress(PluginLoadError):
                    self._load(name)
        return self.failures()

    def __contains__(self, name: object) -> bool:
        return name in self.names()

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def _unknown_message(self, name: str) -> str:
        valid = self.names()
        message = f"unknown {self.kind} {name!r}; valid {self.kind}s: {', '.join(valid) or 'none'}"
        message += did_you_mean(name, valid)
        if not valid:
            message += " (is kkl-bench installed? run `pip install -e .` in the checkout)"
        return message

    def _scan(self) -> None:
        if self._scanned:
            return
        self._scanned = True
        for entry_point in importlib.metadata.entry_points(group=self.group):
            if entry_point.name not in self._loaded:
                self._lazy.setdefault(entry_point.name, entry_point)

    def _load(self, name: str) -> T:
        entry_point = self._lazy.pop(name)
        try:
            obj = entry_point.load()
        except Exception as error:  # a plugin may fail in any way; report it, keep the rest
            reason = f"{entry_point.value}: {type(error).__name__}: {error}"
            self._failed[name] = reason
            raise PluginLoadError(f"{self.kind} {name!r} failed to load: {reason}") from error
        return self.register(name)(obj)


def did_you_mean(name: str, valid: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` naming the closest of ``valid`` to ``name``, or ``""`` if
    none is close: what every unknown-name error of kkl-bench ends with."""
    close = difflib.get_close_matches(name, list(valid), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _natural(name: str) -> list[tuple[int, int | str]]:
    """Sort key: runs of digits compare as numbers, the rest as text."""
    return [(0, int(part)) if part.isdigit() else (1, part) for part in re.split(r"(\d+)", name)]


systems: Registry = Registry("system", "kkl_bench.systems")
regimes: Registry = Registry("regime", "kkl_bench.regimes")
estimators: Registry = Registry("estimator", "kkl_bench.estimators")
