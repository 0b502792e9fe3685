"""The ledger a regeneration (:mod:`kkl_bench.run.regenerate`) keeps beside the results it
writes: each finished fit's measured processor time (its core-seconds, one thread a
fit) and wall time, so that the core-hours of a board are read from what ran, across
interrupted and resumed invocations.

A job killed mid-training (a stopped session, a lost machine) resumes from its
checkpoint in a later invocation, and the time it spent before the kill counts too: a
running job keeps a *meter*, a file of its own under ``<folder>/.meters/`` that it
rewrites every :data:`METER_EVERY_S` seconds with the processor and wall seconds spent
so far, locked while its job lives. When a job finishes, the meters of its earlier,
killed attempts (unlocked ones) are added to its times and removed, so at most one
meter period per kill goes uncounted. The meters travel with the results folder (only
their locks are ignored by git), so a job resumed on a new machine from a committed or
copied folder counts its killed attempts there too.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from filelock import FileLock, Timeout

from kkl_bench.support.provenance import provenance

LEDGER_FILE = "regeneration.json"
METER_FOLDER = ".meters"
METER_EVERY_S = 30.0
"""Seconds between a running job's meter writes: the most a kill leaves uncounted."""


def key_parts(key: str) -> tuple[str, str, int, list[str]]:
    """The row, system, seed and task ids (:attr:`~kkl_bench.suite.task.Task.id`) of a
    job's ledger key (:func:`kkl_bench.run.regenerate.job_key`)."""
    matched = re.fullmatch(r"(.+) (\S+) seed(\d+) \[(.*)\]", key)
    if matched is None:
        raise ValueError(f"not a regeneration ledger key: {key!r}")
    row, system, seed, tasks = matched.groups()
    return row, system, int(seed), tasks.split(",")


def read_ledger(folder: Path) -> dict[str, Any]:
    """The ledger of the regenerations that wrote into ``folder`` (empty if none):
    ``jobs``: key -> ``{seconds, wall_seconds, estimate_s, cells, failed, device,
    git_commit, finished_at}`` (``seconds``: processor time; ``device``: the device its
    torch estimators were given, ``cpu`` or ``cuda``, absent in ledgers from before it was
    recorded, whose jobs ran on the CPU); and, once a regeneration made some cells again
    (:func:`supersede`), ``superseded``: the records of the jobs that had made them, each
    with its ``key``, ``because`` and ``superseded_at``."""
    path = Path(folder) / LEDGER_FILE
    if not path.exists():
        return {"jobs": {}}
    return json.loads(path.read_text())


def record_job(
    into: Path,
    key: str,
    times: dict[str, float],
    estimate_s: float,
    cells: int,
    failed: int,
    device: str = "cpu",
) -> None:
    """Add one finished job (its ``key``, ``times``: ``seconds`` of processor time and
    ``wall_seconds``, its estimate, the cells it made and those that failed, the device its
    torch estimators were given) to the ledger in ``into``, written atomically. A job run
    again (its failed cells retried) adds its times to those before, and the cells it made
    to those it had made without failing. The ledger is read and written under a lock, so
    regenerations into one folder at once (two invocations on disjoint rows or systems,
    or machines sharing the folder) lose none of each other's jobs."""
    commit = provenance()["git_commit"]
    with _ledger_lock(into):
        ledger = read_ledger(into)
        previous = ledger["jobs"].get(key, {})
        ledger["jobs"][key] = {
            **{name: previous.get(name, 0.0) + value for name, value in times.items()},
            "estimate_s": estimate_s,
            "cells": previous.get("cells", 0) - previous.get("failed", 0) + cells,
            "failed": failed,
            "device": device,
            "git_commit": commit,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        _write_atomically(Path(into) / LEDGER_FILE, ledger)


def supersede(into: Path, keys: list[str], because: str) -> None:
    """Move the jobs ``keys`` of the ledger in ``into`` to its ``superseded`` list, each
    with ``because`` (why their cells are made again) and the time: what they spent stays
    in the ledger, apart from the jobs whose cells the folder holds."""
    if not keys:
        return
    with _ledger_lock(into):
        ledger = read_ledger(into)
        now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        ledger.setdefault("superseded", []).extend(
            {"key": key, **ledger["jobs"].pop(key), "because": because, "superseded_at": now}
            for key in keys
        )
        _write_atomically(Path(into) / LEDGER_FILE, ledger)


def _ledger_lock(folder: Path) -> FileLock:
    """The lock of ``folder``'s ledger: a file beside the meters, ignored by git like
    their locks."""
    _prepare_meter_folder(folder)
    return FileLock(Path(folder) / METER_FOLDER / "ledger.lock")


def _prepare_meter_folder(folder: Path) -> None:
    """Create ``folder``'s meter folder, with the ``.gitignore`` that keeps its locks out
    of git."""
    (Path(folder) / METER_FOLDER).mkdir(parents=True, exist_ok=True)
    (Path(folder) / METER_FOLDER / ".gitignore").write_text("*.lock\n")


def _write_atomically(path: Path, record: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(f".{os.getpid()}.tmp")
    temporary.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    os.replace(temporary, path)


def _meter_folder(folder: Path, key: str) -> Path:
    """Where the meters of the job ``key`` live: one folder a job, named by the start of
    its key and a digest of all of it (a job scoring many tasks has a key longer than a
    file name may be)."""
    readable = "".join(c if c.isalnum() or c in "-_.@" else "_" for c in key)[:80]
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return Path(folder) / METER_FOLDER / f"{readable}-{digest}"


@contextlib.contextmanager
def metered(
    folder: Path, key: str, every_s: float = METER_EVERY_S
) -> Iterator[Callable[[], dict[str, float]]]:
    """Keep a meter of the job ``key`` in ``folder`` while the block runs: every
    ``every_s`` seconds its processor seconds (this process's, which runs one job at a
    time) and wall seconds so far are written, under a lock held until the block ends;
    the meter is removed when it ends, however it ends. What a killed process's meter
    holds is added to the job's times when the job next finishes
    (:func:`interrupted_times`). Yields the function that reads the times so far
    (``{"seconds", "wall_seconds"}``, s)."""
    start_cpu, start = time.process_time(), time.perf_counter()
    attempt = f"{socket.gethostname()}-{os.getpid()}-{time.time_ns()}"
    path = _meter_folder(folder, key) / f"{attempt}.json"
    _prepare_meter_folder(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(path.with_suffix(".lock"))
    stopped = threading.Event()

    def spent() -> dict[str, float]:
        return {
            "seconds": time.process_time() - start_cpu,
            "wall_seconds": time.perf_counter() - start,
        }

    def beat() -> None:
        while not stopped.wait(every_s):
            _write_atomically(path, spent())

    with lock:
        _write_atomically(path, spent())
        beat_thread = threading.Thread(target=beat, name=f"meter {key}", daemon=True)
        beat_thread.start()
        try:
            yield spent
        finally:
            stopped.set()
            beat_thread.join()
            path.unlink(missing_ok=True)
    path.with_suffix(".lock").unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # the job's folder, unless another attempt's meter is in it
        path.parent.rmdir()


def interrupted_times(folder: Path, key: str) -> dict[str, float]:
    """The seconds (processor and wall) that killed attempts of the job ``key`` spent, read
    from their meters (those no live process holds), which are then removed."""
    total, removed = {"seconds": 0.0, "wall_seconds": 0.0}, []
    for path, spent in _killed_meters(folder, key):
        for name in total:
            total[name] += float(spent.get(name, 0.0))
        path.unlink()
        removed.append(path)
    for path in removed:  # their locks, released
        path.with_suffix(".lock").unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # gone, or another attempt's meter is in it
        _meter_folder(folder, key).rmdir()
    return total


def killed_attempts(folder: Path, key: str) -> list[dict[str, float]]:
    """What each killed attempt of the job ``key`` spent (``{"seconds", "wall_seconds"}``,
    read from its meter, left in place): the work a resumed job does not do again."""
    return [spent for _, spent in _killed_meters(folder, key)]


def running_seconds(folder: Path, key: str, since_ns: int) -> float:
    """Processor seconds the attempts of the job ``key`` started at or after ``since_ns``
    (:func:`time.time_ns`: this invocation's, which are running or have just ended) have
    spent so far, as their meters last said (at most :data:`METER_EVERY_S` old). Reads
    the meters without their locks, so it can be asked often and creates nothing."""
    total = 0.0
    for path in _meter_folder(folder, key).glob("*.json"):
        started = path.stem.rpartition("-")[2]
        if started.isdigit() and int(started) >= since_ns:
            with contextlib.suppress(OSError, ValueError):  # removed as its job ended
                total += float(json.loads(path.read_text()).get("seconds", 0.0))
    return total


def _killed_meters(folder: Path, key: str) -> Iterator[tuple[Path, dict[str, float]]]:
    """Each meter of the job ``key`` that no live process holds, with what it holds; the
    meter's lock is held while the caller handles it."""
    for path in sorted(_meter_folder(folder, key).glob("*.json")):
        lock = FileLock(path.with_suffix(".lock"))
        try:
            lock.acquire(timeout=0)
        except Timeout:
            continue  # its job is still running
        try:
            yield path, json.loads(path.read_text())
        finally:
            lock.release()


def ledger_summary(ledger: dict[str, Any]) -> dict[str, Any] | None:
    """What the board says of a regeneration: jobs, cells, core-hours measured, the jobs
    that ran with a GPU, the commits that ran them (``commits``: each with the cells its
    jobs made, in the order they first finished one), first and last finish, and the jobs
    whose cells were made again (``superseded``: how many, their core-hours and why), and
    ``rows``: per row, its jobs, cells, core-hours measured and estimated, and its
    costliest system with that system's core-hours, the costliest row first; None without
    one."""
    jobs = ledger.get("jobs", {})
    if not jobs:
        return None
    in_order = sorted(jobs.values(), key=lambda record: record["finished_at"])
    commits: dict[str, int] = {}
    for record in in_order:
        commit = str(record["git_commit"])
        commits[commit] = commits.get(commit, 0) + record["cells"]
    superseded = ledger.get("superseded", [])
    return {
        "jobs": len(jobs),
        "cells": sum(record["cells"] for record in jobs.values()),
        "core_hours": sum(record["seconds"] for record in jobs.values()) / 3600,
        "estimated_core_hours": sum(record["estimate_s"] for record in jobs.values()) / 3600,
        "gpu_jobs": sum(record.get("device", "cpu") == "cuda" for record in jobs.values()),
        "commits": commits,
        "from": in_order[0]["finished_at"],
        "to": in_order[-1]["finished_at"],
        "rows": _core_hours_per_row(jobs),
        "superseded": {
            "jobs": len(superseded),
            "core_hours": sum(record["seconds"] for record in superseded) / 3600,
            "because": list(dict.fromkeys(record["because"] for record in superseded)),
        },
    }


def _core_hours_per_row(jobs: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Per row of the ledger's ``jobs``: jobs, cells, core-hours measured and estimated,
    the costliest system and its core-hours; the row that took most first."""
    rows: dict[str, dict[str, Any]] = {}
    per_system: dict[str, dict[str, float]] = {}
    for key, record in jobs.items():
        row, system, _, _ = key_parts(key)
        totals = rows.setdefault(
            row, {"row": row, "jobs": 0, "cells": 0, "core_hours": 0.0, "estimated_core_hours": 0.0}
        )
        totals["jobs"] += 1
        totals["cells"] += record["cells"]
        totals["core_hours"] += record["seconds"] / 3600
        totals["estimated_core_hours"] += record["estimate_s"] / 3600
        systems = per_system.setdefault(row, {})
        systems[system] = systems.get(system, 0.0) + record["seconds"] / 3600
    for row, totals in rows.items():
        system = max(per_system[row], key=per_system[row].get)
        totals["costliest_system"] = system
        totals["costliest_core_hours"] = per_system[row][system]
    return sorted(rows.values(), key=lambda totals: -totals["core_hours"])
