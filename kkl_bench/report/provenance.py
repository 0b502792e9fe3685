"""How the published numbers were made, read from the cells: versions, commits, and per row
the seeds, tracks and command lines of its runs."""

from __future__ import annotations

import pandas as pd

from kkl_bench.analysis.document import HTML, Section, Table, Text
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.report.board import Board
from kkl_bench.run.results import cell_path
from kkl_bench.run.verification import (
    DRIFTED,
    IDENTICAL,
    VERDICT_COLUMNS,
    WITHIN,
    latest_run,
    verification_sentence,
)
from kkl_bench.support.convergence import trained

NOT_RECORDED = "not recorded"
"""What the Reproduce table says of cells written before runs recorded their command line."""

RUNS_TEXT = (
    "The runs behind these results, as their cells record them: per row, the seeds it ran "
    "on each track, the cells read here, the commits that wrote (scored) them, the commits "
    "whose code trained the models they used (with how many cells each; read from the "
    "training each cell records, `fit_report.spent`) and the command lines of their runs "
    f"(`{NOT_RECORDED}`: cells written before `kkl-bench run` recorded its command line, or "
    "its models' training commit)."
)
DIRTY = "-dirty"
"""The suffix of a commit whose checkout had uncommitted changes (:func:`kkl_bench.support.provenance.provenance`)."""


def training_commits(fit_report: dict | None) -> set[str]:
    """The commits whose code trained a cell's model, as its fit report's ``spent``
    records them per phase (empty where it records none: a filter, or an older cell)."""
    spent = (fit_report or {}).get("spent") or {}
    return {
        str(phase["git_commit"])
        for phase in spent.values()
        if isinstance(phase, dict) and phase.get("git_commit")
    }


def _trained_by(reports) -> str:
    """``41fe503615c0 (462); not recorded (330)``: the training commits of a row's cells
    (``reports``: the fit reports of those it fitted, not of its ``unsupported`` ones, which
    have no model) with how many cells each, empty if no cell trains."""
    if not any(trained(report) for report in reports):
        return ""  # nothing trained (a filter)
    counts: dict[str, int] = {}
    for report in reports:
        for commit in training_commits(report) or {NOT_RECORDED}:
            counts[commit] = counts.get(commit, 0) + 1
    recorded = sorted(c for c in counts if c != NOT_RECORDED)
    parts = [f"`{c}` ({counts[c]})" for c in recorded]
    if NOT_RECORDED in counts:
        parts.append(f"{NOT_RECORDED} ({counts[NOT_RECORDED]})")
    return "; ".join(parts)


def training_commit_sentence(results: pd.DataFrame) -> str:
    """Which commits trained the models of the cells of ``results`` whose rows train (each
    cell's ``fit_report.spent``), with how many cells each: one sentence, empty if no
    cell's model was trained."""
    reports = [report for report in results["fit_report"] if trained(report)]
    if not reports:
        return ""
    counts: dict[str, int] = {}
    for report in reports:
        commits = training_commits(report)
        key = ", ".join(sorted(commits)) if commits else NOT_RECORDED
        counts[key] = counts.get(key, 0) + 1
    if len(counts) == 1 and NOT_RECORDED not in counts:
        (commit,) = counts
        return f"Every one of the {len(reports)} cells of trained models was trained at `{commit}`."
    listed = "; ".join(
        f"{'`' + key + '`' if key != NOT_RECORDED else key} ({count})"
        for key, count in sorted(counts.items(), key=lambda item: -item[1])
    )
    return (
        f"The {len(reports)} cells of trained models were trained at {len(counts)} "
        f"commits or sets of commits (cells each): {listed}."
    )


def dirty_cells(results: pd.DataFrame, verifications: pd.DataFrame | None = None) -> pd.DataFrame:
    """The cells made by code with uncommitted changes: scored, or whose model was trained,
    from a ``-dirty`` checkout. Columns ``cell`` (row, system, track, task, seed),
    ``scored`` and ``trained`` (the dirty commits, empty where that step was clean) and
    ``verified``: the latest verdict of ``verifications`` (the rows of
    ``verification.csv``) that re-derived this very record at a committed tree, empty if
    none did."""
    verdicts = _clean_verdicts(verifications)
    rows = []
    for _, cell in results.iterrows():
        scored = str(cell["provenance"].get("git_commit"))
        trained = sorted(c for c in training_commits(cell.get("fit_report")) if c.endswith(DIRTY))
        if scored.endswith(DIRTY) or trained:
            key = cell_path(
                "",
                cell["estimator"],
                cell["system"],
                cell["regime"],
                "",
                cell["seed"],
                cell["track"],
            )
            rows.append(
                {
                    "cell": f"`{cell['estimator']}` {cell['system']} {cell['track']} "
                    f"{cell['regime']} seed {cell['seed']}",
                    "scored": scored if scored.endswith(DIRTY) else "",
                    "trained": ", ".join(trained),
                    "verified": verdicts.get((key.as_posix(), scored), ""),
                }
            )
    return pd.DataFrame(rows, columns=["cell", "scored", "trained", "verified"])


def _clean_verdicts(verifications: pd.DataFrame | None) -> dict[tuple[str, str], str]:
    """``(cell path, published commit) -> verdict`` of the latest verification of each
    record made at a committed tree."""
    if verifications is None or verifications.empty:
        return {}
    clean = verifications[~verifications["verified_commit"].astype(str).str.endswith(DIRTY)]
    latest = clean.sort_values("run").groupby(["cell", "published_commit"])["verdict"].last()
    return {(str(cell), str(commit)): verdict for (cell, commit), verdict in latest.items()}


def dirty_sentence(dirty: pd.DataFrame, total: int) -> str:
    """What the board says of its cells made from uncommitted code (:func:`dirty_cells`)."""
    if dirty.empty:
        return f"Every one of the {total} cells was scored, and its model trained, from a committed tree."
    scored = int((dirty["scored"] != "").sum())
    trained = int((dirty["trained"] != "").sum())
    counts = dirty.loc[dirty["verified"] != "", "verified"].value_counts()
    re_derived = (
        f"; {int(counts.sum())} of them re-derived since by `kkl-bench verify` at a committed "
        f"tree: {counts.get(IDENTICAL, 0)} identical, {counts.get(WITHIN, 0)} within "
        f"its tolerance, {counts.get(DRIFTED, 0)} drifted"
        if not counts.empty
        else ""
    )
    return (
        f"{len(dirty)} of the {total} cells were made by code with uncommitted changes "
        f"(a commit ending `{DIRTY}`): {scored} scored and {trained} trained from such a "
        "tree; their numbers cannot be re-derived from a commit alone (`kkl-bench verify` "
        f"re-derives them from the current one){re_derived}. Per row (each cell on the page):"
    )


def failed_seeds(results: pd.DataFrame) -> dict[str, list[int]]:
    """Row -> the seeds of ``results`` with a cell whose estimator failed (status error)."""
    failed = results[results["status"] == "error"]
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
        fitted = cells[cells["status"] != "unsupported"] if "status" in cells else cells
        reports = fitted["fit_report"] if "fit_report" in fitted else [None] * len(fitted)
        rows.append(
            {
                "estimator": f"`{name}`",
                "seeds": "; ".join(
                    f"{seed_list} on {', '.join(tracks)}" for seed_list, tracks in by_seeds.items()
                ),
                "cells": len(cells),
                "commits": ", ".join(sorted(set(cells["commit"]))),
                "trained": _trained_by(list(reports)),
                "commands": "<br>".join(c if c == NOT_RECORDED else f"`{c}`" for c in commands),
            }
        )
    return pd.DataFrame(rows)


RUN_COLUMNS = {
    "estimator": "Row",
    "seeds": "Seeds on tracks",
    "cells": "Cells",
    "commits": "Commits",
    "trained": "Trained by",
    "commands": "Command lines",
}


def provenance_facts(results: pd.DataFrame) -> dict[str, list[str]]:
    """Distinct protocol, package versions, commits, Pythons and platforms in the results
    (a platform with the cells written on it, where there are several: a trained model
    can come out otherwise on another processor, protocol section 9)."""
    facts: dict[str, set[str]] = {"protocol": set(results["protocol"])}
    platforms: dict[str, int] = {}
    for record in results["provenance"]:
        for package, version in record.get("versions", {}).items():
            facts.setdefault(package, set()).add(version)
        facts.setdefault("git commit", set()).add(str(record.get("git_commit")))
        facts.setdefault("python", set()).add(str(record.get("python")))
        platform = str(record.get("platform"))
        platforms[platform] = platforms.get(platform, 0) + 1
    if len(platforms) > 1:
        facts["platform"] = {
            f"{name} ({count} cell{'s' * (count != 1)})" for name, count in platforms.items()
        }
    elif platforms:
        facts["platform"] = set(platforms)
    return {key: sorted(values) for key, values in facts.items()}


def regeneration_sentence(summary: dict | None, cells: int) -> str:
    """What the Reproduce section says of the ``kkl-bench regenerate`` runs that wrote the
    results (:func:`kkl_bench.run.regenerate.ledger_summary` of their ledger), of the
    board's ``cells``."""
    if summary is None:
        return (
            "These results were not written by `kkl-bench regenerate` (their folder holds no "
            "ledger of one): the core-hours they took are not recorded."
        )
    commits = ", ".join(
        f"{commit} ({count} cell{'s' * (count != 1)})"
        for commit, count in summary["commits"].items()
    )
    share = (
        f"all {cells} cells"
        if summary["cells"] >= cells
        else f"{summary['cells']} of the {cells} cells (the others' runs are listed below)"
    )
    on_gpu = (
        f"; {summary['gpu_jobs']} of the jobs ran with `--device cuda`, whose GPU time this "
        "does not count"
        if summary.get("gpu_jobs")
        else ""
    )
    return (
        f"Written by `kkl-bench regenerate`: {share}, by {summary['jobs']} jobs (fits, and "
        f"jobs that only scored trained models), in **{summary['core_hours']:.1f} "
        f"core-hours** measured (processor time, one thread a job{on_gpu}; "
        f"{summary['estimated_core_hours']:.1f} estimated beforehand), "
        f"at commit{'s' if len(summary['commits']) > 1 else ''} {commits}, the jobs "
        f"finishing between {summary['from']} and {summary['to']}.{_superseded(summary)}"
    )


CORE_HOURS_TEXT = (
    "Where the regeneration's core-hours went, per row, from its ledger (the jobs whose "
    "cells the folder holds; a model several rows use, as the KKL rows' Phase 1, counts in "
    "the job that trained it, the first to need it):"
)
CORE_HOURS_COLUMNS = {
    "row": "Row",
    "jobs": "Jobs",
    "cells": "Cells",
    "core_hours": "Core-hours",
    "estimated_core_hours": "Estimated",
    "costliest": "Costliest system (core-hours)",
}


def core_hours_per_row(summary: dict | None) -> list[Text | Table]:
    """The text and table of a regeneration's core-hours per row
    (:func:`kkl_bench.run.ledger.ledger_summary`'s ``rows``); nothing without one."""
    if summary is None:
        return []
    rows = pd.DataFrame(summary["rows"]).assign(
        row=lambda frame: "`" + frame["row"] + "`",
        costliest=lambda frame: [
            f"{system} ({hours:.2f})"
            for system, hours in zip(
                frame["costliest_system"], frame["costliest_core_hours"], strict=True
            )
        ],
    )
    return [
        Text(CORE_HOURS_TEXT),
        Table(rows, CORE_HOURS_COLUMNS, id="core-hours", floatfmt=".2f"),
    ]


def _superseded(summary: dict) -> str:
    """The sentence on the jobs whose cells a regeneration made again (``kkl-bench
    regenerate --redo``), with the reasons they were given; empty if none."""
    superseded = summary.get("superseded", {})
    if not superseded.get("jobs"):
        return ""
    return (
        f" Besides, {superseded['jobs']} earlier jobs took "
        f"{superseded['core_hours']:.1f} core-hours whose cells were made again at a later "
        f"commit ({'; '.join(superseded['because'])})."
    )


def provenance_sections(board: Board) -> list[Section]:
    seeds = ", ".join(map(str, sorted(set(board.results["seed"]))))
    facts = [("seeds", seeds)] + [
        (key, ", ".join(values)) for key, values in provenance_facts(board.results).items()
    ]
    versions = pd.DataFrame(facts, columns=["what", "value"])
    cells = board.cells_of_every_track
    dirty = dirty_cells(cells, board.verifications)
    listed = [Text(dirty_sentence(dirty, len(cells)))]
    if not dirty.empty:
        per_row = (
            dirty.assign(
                row=dirty["cell"].str.split(" ").str[0],
                reproduced=dirty["verified"].isin([IDENTICAL, WITHIN]),
            )
            .groupby(["row", "scored", "trained"], sort=False)
            .agg(cells=("cell", "size"), reproduced=("reproduced", "sum"))
            .reset_index()
        )
        columns = {"scored": "Scored at", "trained": "Trained at"}
        listed.append(
            Table(
                per_row,
                {"row": "Row", **columns, "cells": "Cells", "reproduced": "Re-derived at a commit"},
                id="dirty-rows",
            )
        )
        folded = f"Every cell made from uncommitted code ({len(dirty)} rows)"
        listed.append(
            Table(
                dirty,
                {"cell": "Cell", **columns, "verified": "Verified"},
                id="dirty-cells",
                folded=folded,
                only=HTML,
            )
        )
    checked = [Text(verification_sentence(board.verifications))]
    if board.verifications is not None and not board.verifications.empty:
        latest = latest_run(board.verifications).assign(
            cell=lambda frame: "`" + frame["cell"] + "`"
        )
        checked.append(Table(latest, VERDICT_COLUMNS, id="verification"))
    made_by = (
        regeneration_sentence(board.regeneration, len(cells)),
        training_commit_sentence(cells),
    )
    return [
        Section("Provenance", [Table(versions, id="provenance")]),
        Section(
            "Reproduce",
            [
                Text(" ".join(sentence for sentence in made_by if sentence)),
                *core_hours_per_row(board.regeneration),
                Text(RUNS_TEXT),
                Table(board.runs, RUN_COLUMNS, id="runs"),
                *listed,
                *checked,
            ],
        ),
    ]
