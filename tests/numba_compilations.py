"""What the test run spends compiling numba functions, test by test (``--numba-compilations``).

A pytest plugin (:data:`tests.conftest.pytest_plugins`): with ``--numba-compilations
PATH``, every compilation numba starts inside a test process (its ``numba:compile``
event: a function compiled for a signature, not one loaded from the on-disk cache) is
timed, and the outermost ones are written to ``PATH`` as JSON lines, one per test:
``{"test": nodeid, "compilations": [[module.qualname, seconds], ...]}``. Under pytest-xdist
each worker writes ``PATH.<worker>``; the run ends with the total and the costliest tests.
Compilations in a command a test starts as a subprocess are not counted.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

OPTION = "--numba-compilations"
SHOWN = 15
"""How many of the costliest tests the run's summary lists."""


def pytest_addoption(parser):
    parser.addoption(
        OPTION,
        metavar="PATH",
        help="write each test's numba compilations (function, seconds) to PATH as JSON lines",
    )


class _Recorder:
    """Times the outermost numba compilations between two :meth:`take` calls."""

    def __init__(self):
        self.started: list[float] = []
        self.finished: list[tuple[str, float]] = []

    def on_start(self, event) -> None:
        self.started.append(time.perf_counter())

    def on_end(self, event) -> None:
        seconds = time.perf_counter() - self.started.pop()
        if not self.started:  # a compilation inside another is part of that one
            function = event.data["dispatcher"].py_func
            self.finished.append((f"{function.__module__}.{function.__qualname__}", seconds))

    def take(self) -> list[tuple[str, float]]:
        taken, self.finished = self.finished, []
        return taken


def _written(path: str) -> list[Path]:
    """The files a run with ``--numba-compilations path`` writes: ``path`` and its workers'."""
    path = Path(path)
    return sorted([path, *path.parent.glob(path.name + ".*")])


def pytest_configure(config):
    path = config.getoption(OPTION)
    if path is None:
        return
    worker = getattr(config, "workerinput", {}).get("workerid")
    if worker is None:  # the run's own process (before any worker starts): a clean slate
        for file in _written(path):
            file.unlink(missing_ok=True)
    from numba.core import event

    recorder = _Recorder()

    class Listener(event.Listener):
        def on_start(self, event):
            recorder.on_start(event)

        def on_end(self, event):
            recorder.on_end(event)

    event.register("numba:compile", Listener())
    config.stash[_KEY] = (recorder, Path(f"{path}.{worker}" if worker else path))


_KEY = pytest.StashKey[tuple[_Recorder, Path]]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    recording = item.config.stash.get(_KEY, None)
    if recording is not None:
        recording[0].take()  # nothing from between tests
    yield
    if recording is not None:
        recorder, output = recording
        line = {"test": item.nodeid, "compilations": recorder.take()}
        with output.open("a") as file:
            file.write(json.dumps(line) + "\n")


def pytest_terminal_summary(terminalreporter, config):
    path = config.getoption(OPTION)
    if path is None or hasattr(config, "workerinput"):
        return
    files = [file for file in _written(path) if file.is_file()]
    records = [json.loads(line) for file in files for line in file.read_text().splitlines()]
    per_test = sorted(
        ((sum(s for _, s in r["compilations"]), r["test"]) for r in records), reverse=True
    )
    total = sum(seconds for seconds, _ in per_test)
    compiled = sum(len(r["compilations"]) for r in records)
    terminalreporter.write_sep("=", "numba compilations")
    terminalreporter.write_line(
        f"{compiled} compilations, {total:.0f} s in the test processes (written to "
        f"{', '.join(map(str, files))})"
    )
    for seconds, test in per_test[:SHOWN]:
        if seconds > 0:
            terminalreporter.write_line(f"{seconds:8.1f} s  {test}")
