"""How the published numbers were made, read from the cells: versions, commits, and per row
the seeds, tracks and command lines of its runs."""

from __future__ import annotations

import pandas as pd

from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.report.board import Board
from kkl_bench.report.model import Section, Table, Text
from kkl_bench.verification import VERDICT_COLUMNS, latest_run, verification_sentence

NOT_RECORDED = "not recorded"
"""What the Reproduce table says of cells written before runs recorded their command line."""

RUNS_TEXT = (
    "The runs behind these results, as their cells record them: per row, the seeds it ran "
    "on each track, the cells read here, the commits that wrote them and the command lines of "
    f"their runs (`{NOT_RECORDED}`: cells written before `kkl-bench run` recorded its "
    "command line)."
)


def failed_seeds(results: pd.DataFrame) -> dict[str, list[int]]:
    """Row -> the seeds of ``results`` with a cell whose estimator failed (status error)."""
    failed = results[results["status"] != "ok"]
    return {name: sorted(set(cells["seed"])) for name, cells in failed.groupby("estimator")}


def _in_track_order(tracks: set[str]) -> list[str]:
    first = [PAPER_TRACK] if PAPER_TRACK in tracks else []
    return first + sorted(tracks - {PAPER_TRACK})


def runs_frame(results: pd.DataFrame) -> pd.DataFrame:
    """Per result row: the seeds it ran on each track (``0, 1, 2 on paper; 0 on noise``),
    its cells, the commits that wrote them and the command lines its runs recorded (in
    the order first used, one per line), read from the cells."""
    rows = []
    for name, cells in results.groupby("estimator", sort=False):
        cells = cells.assign(
            command=[record.get("command") or NOT_RECORDED for record in cells["provenance"]],
            commit=[str(record.get("git_commit")) for record in cells["provenance"]],
            written=[str(record.get("written_at", "")) for record in cells["provenance"]],
        ).sort_values("written")
        seeds = cells.groupby("track")["seed"].agg(lambda s: ", ".join(map(str, sorted(set(s)))))
        by_seeds: dict[str, list[str]] = {}
        for track in _in_track_order(set(seeds.index)):
            by_seeds.setdefault(seeds[track], []).append(track)
        commands = dict.fromkeys(cells["command"])
        rows.append(
            {
                "estimator": f"`{name}`",
                "seeds": "; ".join(
                    f"{seed_list} on {', '.join(tracks)}" for seed_list, tracks in by_seeds.items()
                ),
                "cells": len(cells),
                "commits": ", ".join(sorted(set(cells["commit"]))),
                "commands": "<br>".join(c if c == NOT_RECORDED else f"`{c}`" for c in commands),
            }
        )
    return pd.DataFrame(rows)


RUN_COLUMNS = {
    "estimator": "Row",
    "seeds": "Seeds on tracks",
    "cells": "Cells",
    "commits": "Commits",
    "commands": "Command lines",
}


def _versions(results: pd.DataFrame) -> dict[str, list[str]]:
    """Distinct protocol, package versions, commits and Pythons in the results."""
    facts: dict[str, set[str]] = {"protocol": set(results["protocol"])}
    for record in results["provenance"]:
        for package, version in record.get("versions", {}).items():
            facts.setdefault(package, set()).add(version)
        facts.setdefault("git commit", set()).add(str(record.get("git_commit")))
        facts.setdefault("python", set()).add(str(record.get("python")))
    return {key: sorted(values) for key, values in facts.items()}


def provenance_sections(board: Board) -> list[Section]:
    seeds = ", ".join(map(str, sorted(set(board.results["seed"]))))
    facts = [("seeds", seeds)] + [
        (key, ", ".join(values)) for key, values in _versions(board.results).items()
    ]
    versions = pd.DataFrame(facts, columns=["what", "value"])
    checked = [Text(verification_sentence(board.verifications))]
    if board.verifications is not None and not board.verifications.empty:
        latest = latest_run(board.verifications).assign(
            cell=lambda frame: "`" + frame["cell"] + "`"
        )
        checked.append(Table(latest, VERDICT_COLUMNS, id="verification"))
    return [
        Section("Provenance", [Table(versions, id="provenance")]),
        Section(
            "Reproduce",
            [Text(RUNS_TEXT), Table(board.runs, RUN_COLUMNS, id="runs"), *checked],
        ),
    ]
