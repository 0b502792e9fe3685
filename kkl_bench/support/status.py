"""What each running job is doing now, for the progress line of ``kkl-bench run``.

A job (fit one estimator on one system, score it) may run in this process or
in a worker process. It states what it is doing in a small file of its own,
``<results>/.claims/<profile>/<job>.status``, through :func:`reporting`; the
training loops add how far they are (:func:`step`, at most once a second).
The command that started the run reads every status file of its profile
(:func:`current`) and shows them beside its progress bar. The files are
removed when their job ends; one left by a killed run is not shown: it is older
than the run that reads it, or it names a process of this machine that is gone.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

SUFFIX = ".status"
INTERVAL_S = 1.0
"""Training writes its progress at most this often."""


class _Status:
    """The status file of one job and what it says."""

    def __init__(self, path: Path, job: str) -> None:
        self.path, self.job, self.written = path, job, 0.0

    def write(self, text: str) -> None:
        partial = self.path.with_name(self.path.name + ".partial")
        try:
            partial.write_text(f"{_WRITER}\n{self.job}: {text}")
            os.replace(partial, self.path)
        except OSError:  # progress is a courtesy: never fail a job for it
            pass
        self.written = time.monotonic()


_WRITER = f"{socket.gethostname()} {os.getpid()}"
"""The first line of a status file: the machine and process that write it."""

_CURRENT: contextvars.ContextVar[_Status | None] = contextvars.ContextVar(
    "kkl_bench_status", default=None
)


def status_path(claims: Path, job: str) -> Path:
    """Where the status of ``job`` (a lock file's stem) lives in the claims folder."""
    return Path(claims) / f"{job}{SUFFIX}"


@contextlib.contextmanager
def reporting(path: Path, job: str) -> Iterator[None]:
    """Inside the block, :func:`say` and :func:`step` write the status of ``job`` (a
    human-readable name, such as ``dynamic_hyperkkl on lorenz, seed 0``) to ``path``;
    the file is removed after it."""
    status = _Status(Path(path), job)
    token = _CURRENT.set(status)
    try:
        yield
    finally:
        _CURRENT.reset(token)
        Path(path).unlink(missing_ok=True)


def say(text: str) -> None:
    """State what the current job does now (``fitting``, ``scoring sinusoid``)."""
    status = _CURRENT.get()
    if status is not None:
        status.write(text)


def step(what: str, done: int, total: int) -> None:
    """Training progress: ``done`` of ``total`` steps of ``what`` (written at most once a
    second, and at the last step)."""
    status = _CURRENT.get()
    if status is not None and (done == total or time.monotonic() - status.written >= INTERVAL_S):
        status.write(f"{what} {done}/{total}")


def current(claims: Path, since: float) -> list[str]:
    """What every job with a status file under ``claims`` written at or after ``since``
    (a ``time.time()``) by a process still running says, sorted by job."""
    texts = []
    for path in sorted(Path(claims).glob(f"*{SUFFIX}")):
        with contextlib.suppress(OSError):
            if path.stat().st_mtime >= since:
                writer, _, text = path.read_text().partition("\n")
                if _running(writer):
                    texts.append(text)
    return texts


def _running(writer: str) -> bool:
    """Whether the process ``writer`` (``<machine> <pid>``) may still run: False only for
    a process of this machine that is gone (another machine's cannot be asked)."""
    machine, _, pid = writer.rpartition(" ")
    if machine != socket.gethostname() or not pid.isdigit():
        return True
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process, running
        pass
    return True
