"""The ledger a regeneration (:mod:`kkl_bench.run.regenerate`) keeps beside the results it
writes: each finished fit's measured processor time (its core-seconds, one thread a
fit) and wall time, so that the core-hours of a board are read from what ran, across
interrupted and resumed invocations."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from kkl_bench.support.provenance import provenance

LEDGER_FILE = "regeneration.json"


def read_ledger(folder: Path) -> dict[str, Any]:
    """The ledger of the regenerations that wrote into ``folder`` (empty if none):
    ``jobs``: key -> ``{seconds, wall_seconds, estimate_s, cells, failed, git_commit,
    finished_at}`` (``seconds``: processor time)."""
    path = Path(folder) / LEDGER_FILE
    if not path.exists():
        return {"jobs": {}}
    return json.loads(path.read_text())


def record_job(
    into: Path, key: str, times: dict[str, float], estimate_s: float, cells: int, failed: int
) -> None:
    """Add one finished job (its ``key``, ``times``: ``seconds`` of processor time and
    ``wall_seconds``, its estimate, the cells it made and those that failed) to the ledger
    in ``into``, written atomically; a job run again adds its times to those before."""
    ledger = read_ledger(into)
    previous = ledger["jobs"].get(key, {})
    ledger["jobs"][key] = {
        **{name: previous.get(name, 0.0) + value for name, value in times.items()},
        "estimate_s": estimate_s,
        "cells": cells,
        "failed": failed,
        "git_commit": provenance()["git_commit"],
        "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    path = Path(into) / LEDGER_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps(ledger, indent=1, sort_keys=True) + "\n")
    os.replace(temporary, path)


def ledger_summary(ledger: dict[str, Any]) -> dict[str, Any] | None:
    """What the board says of a regeneration: jobs, cells, core-hours measured, the
    commits that ran them, first and last finish; None without one."""
    jobs = ledger.get("jobs", {})
    if not jobs:
        return None
    finished = sorted(record["finished_at"] for record in jobs.values())
    return {
        "jobs": len(jobs),
        "cells": sum(record["cells"] for record in jobs.values()),
        "core_hours": sum(record["seconds"] for record in jobs.values()) / 3600,
        "estimated_core_hours": sum(record["estimate_s"] for record in jobs.values()) / 3600,
        "commits": sorted({str(record["git_commit"]) for record in jobs.values()}),
        "from": finished[0],
        "to": finished[-1],
    }
