"""``kkl-bench publish``: the whole ``leaderboard/`` folder from stored results alone.

Writes, for one profile:

* ``README.md``: how to read the tables (spread, marks, seeds), the
  leaderboard in the paper's layout with the paper's rows, our RMSE over the
  paper's, the cost and budget table, the figures, every other track's table
  and their summary relative to the paper track, provenance (protocol and
  package versions, commits) and the commands that made it;
* ``<profile>.tex`` (booktabs) and ``<profile>.csv`` (tidy numbers), and
  ``<profile>-<track>.tex`` / ``.csv`` for every other track;
* ``figures/``: PNG (for the Markdown) and SVG (for the page);
* ``index.html``: a static, self-contained page (no server, no network):
  tables sortable by any column and filterable by system and regime, the
  figures, provenance and the commands.

Nothing is timed or dated here, so the same results give byte-identical files.
"""

from __future__ import annotations

import html
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from tabulate import tabulate

from kkl_bench import figures, findings, variants
from kkl_bench.cost import COST_FILE, read_costs, with_measured_costs
from kkl_bench.leaderboard import (
    COST_COLUMNS,
    LIMIT_COLUMNS,
    PAPER_PREFIX,
    REGIME_TITLES,
    SYSTEM_TITLES,
    cost_frame,
    cost_table,
    limit_frame,
    limit_table,
    measured_cost_table,
    paper_comparison,
    render,
    render_track_summary,
    summary_table,
    track_summary,
)
from kkl_bench.protocol.metrics import SETTLING_THRESHOLD, SETTLING_WINDOW_S
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import estimators
from kkl_bench.results import kept_estimates
from kkl_bench.scaling import TRACK as SCALING_TRACK
from kkl_bench.significance import MARGIN
from kkl_bench.task import ProfileError, get_profile
from kkl_bench.tracks import find_track

MANIFEST = "publication.json"
"""The file by which ``publish`` owns its folder: profile, results folder and files written."""
NOT_RECORDED = "not recorded"
"""What the Reproduce table says of cells written before runs recorded their command line."""


class PublishRefused(ValueError):
    """The output folder holds a board this publication must not overwrite."""


def runs_frame(results: pd.DataFrame) -> pd.DataFrame:
    """Per result row: the seeds it ran on each track (``0, 1, 2 on paper; 0 on noise``),
    its cells, the commits that wrote them and the command lines its runs recorded (in
    the order first used), read from the cells."""
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
        rows.append(
            {
                "estimator": name,
                "seeds": "; ".join(
                    f"{seed_list} on {', '.join(tracks)}" for seed_list, tracks in by_seeds.items()
                ),
                "cells": len(cells),
                "commits": ", ".join(sorted(set(cells["commit"]))),
                "commands": list(dict.fromkeys(cells["command"])),
            }
        )
    return pd.DataFrame(rows)


def _in_track_order(tracks: set[str]) -> list[str]:
    return (
        [PAPER_TRACK, *sorted(tracks - {PAPER_TRACK})] if PAPER_TRACK in tracks else sorted(tracks)
    )


def _runs_markdown(runs: pd.DataFrame) -> str:
    def commands(recorded: list[str]) -> str:
        return "<br>".join(c if c == NOT_RECORDED else f"`{c}`" for c in recorded)

    rows = [
        [
            f"`{row.estimator}`",
            row.seeds,
            row.cells,
            row.commits,
            commands(row.commands),
        ]
        for row in runs.itertuples()
    ]
    return tabulate(
        rows,
        headers=["Row", "Seeds on tracks", "Cells", "Commits", "Command lines"],
        tablefmt="github",
        disable_numparse=True,
    )


def _provenance(results: pd.DataFrame) -> dict[str, list[str]]:
    """Distinct protocol, package versions, commits and Pythons in the results."""
    facts: dict[str, set[str]] = {"protocol": set(results["protocol"])}
    for record in results["provenance"]:
        for package, version in record.get("versions", {}).items():
            facts.setdefault(package, set()).add(version)
        facts.setdefault("git commit", set()).add(str(record.get("git_commit")))
        facts.setdefault("python", set()).add(str(record.get("python")))
    return {key: sorted(values) for key, values in facts.items()}


def _reading_guide(summary: pd.DataFrame, margin: float, failed: dict[str, list[int]]) -> str:
    ours = {e for e in summary["estimator"] if not e.startswith(PAPER_PREFIX)}
    installed = set(estimators.names())  # publishing needs no plugin; those installed say more
    bases = {e: variants.base_name(e) for e in ours}
    single = sorted(
        e for e in ours if bases[e] in installed and not estimators.get(bases[e]).uses_seed
    )
    seeds = int(summary["n_seeds"].max())
    fewer = summary[summary["estimator"].isin(set(ours) - set(single))]
    fewer = fewer.groupby("estimator")["n_seeds"].max()
    fewer = fewer[fewer < seeds]
    short = (
        " Rows that depend on the seed but ran fewer seeds ("
        + ", ".join(f"`{name}`: {count}" for name, count in fewer.items())
        + ") show the spread over the seeds they ran, none for a single seed."
        if len(fewer)
        else ""
    )
    failures = (
        " Some cells failed (the estimator raised; `kkl-bench run` with the same arguments "
        "retries them), and those rows show only the seeds that did not: "
        + "; ".join(
            f"`{name}`: seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))} failed"
            for name, seeds in failed.items()
        )
        + "."
        if failed
        else ""
    )
    return f"""Each cell reads `RMSE ± std (SMAPE %)`: for every training seed, the mean
over the test trajectories of the steady-state RMSE; then the mean of those
over the seeds, `±` their standard deviation over the seeds (sample standard
deviation), and the mean SMAPE in parentheses. The `Seeds` column says how
many seeds each row ran (up to {seeds}); the test trajectories are the same
for every seed and estimator. Estimators that do not depend on the seed
({", ".join(f"`{n}`" for n in single) or "none"}) were run once and show no spread.{short}{failures}

**Bold** marks the lowest RMSE of a column only where it beats every other
entry by a paired hierarchical bootstrap: 4000 resamples that draw the test
trajectories with replacement (the same draws for both estimators) and each
estimator's seeds with replacement; the best entry is bold when the 5 %
quantile of `RMSE(other) / RMSE(best)` is above {1 + margin:g} against every other entry
(a margin of practical equivalence of {100 * margin:g} %: a lead smaller than that is
never a win, however many trajectories agree on it). Otherwise the lowest entry
and every entry not distinguishable from it in that way are in *italics*
(tied). Entries with a diverged trajectory are never marked. The paper's rows
(`paper:`) are its published numbers on its own test sets, shown for
reference and never marked. `kkl_bench/significance.py` has
the exact procedure."""


def _settling(name: str) -> bool:
    track = find_track(name)
    return track is not None and track.settling


@dataclass(frozen=True)
class TrackTables:
    """What the folder shows of the tracks other than the paper's.

    summaries: track name -> its :func:`summary_table`; relative: :func:`track_summary`
    (each track against the paper track); conditions: the same by condition.
    """

    summaries: dict[str, pd.DataFrame]
    relative: pd.DataFrame
    conditions: pd.DataFrame

    @classmethod
    def of(cls, results: pd.DataFrame, margin: float = MARGIN) -> TrackTables:
        others = results[results["track"] != PAPER_TRACK]
        summaries = {
            name: summary_table(cells, margin=margin) for name, cells in others.groupby("track")
        }
        if not summaries:
            return cls({}, pd.DataFrame(), pd.DataFrame())
        return cls(summaries, track_summary(results), track_summary(results, by_condition=True))


def _grouped_conditions(conditions: pd.DataFrame, name: str) -> pd.DataFrame | None:
    """Track ``name``'s rows of ``conditions`` (:func:`track_summary` by condition) if its
    tasks group into fewer conditions than tasks (``mismatch``: ``params10``, ``params25``,
    ``sensor``), else None."""
    track = find_track(name)
    if track is None or conditions.empty:
        return None
    rows = conditions[conditions["track"] == name]
    grouped = 1 < rows["condition"].nunique() < len(track.tasks)
    return rows if grouped else None


CONDITIONS_TEXT = (
    "By condition: the ratio to the estimator's own paper-track RMSE as above, its "
    "geometric mean taken over the systems and regimes of each condition."
)


def _tracks_markdown(
    tables: TrackTables, figure_names: list[str], scaling_study: bool = False
) -> str:
    """The README section of the tracks other than the paper's (empty if there are none);
    ``scaling_study``: link the study ``kkl-bench scaling`` wrote beside it."""
    tracks = tables.summaries
    if not tracks:
        return ""
    trajectories = {
        name: "\n"
        + "\n".join(
            f"![{figure}](figures/{figure}.png)"
            for figure in figure_names
            if figure.startswith(f"track-{name}-")
        )
        + "\n"
        for name in tracks
    }
    sections = []
    for name, summary in tracks.items():
        track = find_track(name)
        description = f"{track.description} " if track else ""
        settling = (
            f"\n\nBeside each RMSE, `settle (s)` is the median over trajectories of the "
            f"settling time: the start of the first {SETTLING_WINDOW_S:g}-second window "
            f"from which on every window's normalized RMSE (error over the test set's state "
            f"standard deviation) stays below {SETTLING_THRESHOLD:g}; `never` counts the "
            "trajectories that never settle."
            if _settling(name)
            else ""
        )
        scaling = (
            "\n\nHow each estimator's fit time, online cost and RMSE grow with Lorenz-96's "
            "dimension: the [scaling study](scaling.md) (`kkl-bench scaling`)."
            if scaling_study and name == SCALING_TRACK
            else ""
        )
        grouped = _grouped_conditions(tables.conditions, name)
        by_condition = (
            f"{CONDITIONS_TEXT}\n\n{render_track_summary(grouped, 'condition')}\n\n"
            if grouped is not None
            else ""
        )
        sections.append(
            f"""### Track `{name}`

{description}Task ids read `{name}/<system>/<task>@v<n>`; `docs/protocol.md` (sections 7
and 8) defines every task.{settling}{scaling}

{render(summary, "markdown", settling=_settling(name))}

{by_condition}![{name}: RMSE relative to the UKF](figures/relative-rmse-{name}.png)
{trajectories.get(name, "")}
"""
        )
    return f"""## Tracks: where methods break

Every estimator is fitted once, exactly as for the paper's track (sensor
noise 0.01, the paper's x0 boxes, its own training inputs), and scored on
each track's test sets as well: the tracks test generalization, never
retraining. The one exception is a `+logged` row of the `mismatch` track:
the estimator fitted again per true plant, with the data logged on it.
Marks and spread read as above.

### Each track relative to the paper track

Per estimator: for every cell of the track, its mean RMSE over the
trajectories that did not diverge, divided by its own paper-track RMSE on
the same system under the regime the track's task names as its reference
(for example a chirp against the paper's sinusoid); the geometric mean of
these ratios over the track's cells. Below 1: better than on the paper track.
Diverged trajectories are left out of the ratio and counted beside it.

{render_track_summary(tables.relative)}

{"".join(sections)}"""


def _limit_markdown(summary: pd.DataFrame) -> str:
    table = limit_table(summary)
    if not table:
        return ""
    return f"""
## Distance from the Bayes limit

`particle_filter` estimates the posterior mean under the exact model (protocol
section 6.1): no estimator can expect a lower RMSE. Each row divides the
EKF's, the UKF's and the best learned row's RMSE by it (1.00: at the limit;
a ratio a little below 1 is the particle filter's own Monte Carlo error).

{table}
"""


def _cost_source(costs: pd.DataFrame | None) -> str:
    """Where the estimation column comes from: a ``kkl-bench cost`` measurement, or the
    scoring runs."""
    if costs is None or costs.empty:
        return (
            "Estimation times are the wall times of the runs that scored the cells: "
            "several runs on different commits and machine loads, so rows compare only "
            "roughly (`kkl-bench cost` times them side by side)."
        )
    commits = ", ".join(sorted(set(costs["git_commit"].astype(str))))
    threads = ", ".join(map(str, sorted(set(costs["threads"]))))
    return (
        f"Estimation times come from one `kkl-bench cost` run ([`{COST_FILE}`]({COST_FILE}), "
        f"commit {commits}): every row's trained models (seed "
        f"{', '.join(map(str, sorted(set(costs['seed']))))}) timed in turn on each test "
        f"set of {', '.join(map(str, sorted(set(costs['trajectories']))))} trajectories, "
        f"{threads} thread(s), best of up to "
        f"{costs['rounds'].max()} timings; rows it did not time show their scoring runs' "
        "wall times."
    )


def _measured_cost_markdown(costs: pd.DataFrame | None) -> str:
    """The side-by-side measurement per system, with each row's ratio to the EKF's cost."""
    if costs is None or costs.empty:
        return ""
    return f"""
Online cost from the same measurement, per system (mean over regimes), the
largest cell, and the EKF's cost over each row's:

{measured_cost_table(costs)}
"""


@dataclass(frozen=True)
class Board:
    """Everything one publication shows, read from the results once for both renderings.

    summary: the paper track's :func:`summary_table` with the paper's rows; results: the
    paper track's cells; runs: :func:`runs_frame` of every track's cells; failed: row ->
    the seeds with a failed paper-track cell; results_link: the results folder relative
    to the published one; smoke: the profile is a smoke test (no findings, no ratios to
    the paper); margin: the marks' practical-equivalence margin.
    """

    summary: pd.DataFrame
    results: pd.DataFrame
    profile: str
    figure_names: list[str]
    tables: TrackTables
    runs: pd.DataFrame
    failed: dict[str, list[int]]
    results_link: str
    smoke: bool
    margin: float
    scaling_study: bool = False
    costs: pd.DataFrame | None = None

    @property
    def guide(self) -> str:
        return _reading_guide(self.summary, self.margin, self.failed)


SMOKE_BANNER = (
    "**A smoke test.** Profile `{profile}` runs the whole pipeline on tiny training "
    "budgets and a few test trajectories: its numbers say nothing about the methods. "
    "The paper's findings and the ratios to the paper's numbers are left out."
)
SMOKE_OMITTED = (
    "Left out: profile `{profile}` is a smoke test, whose numbers say nothing about the "
    "methods (publish a `standard` run for this section)."
)
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


def _markdown(board: Board) -> str:
    summary, results, profile = board.summary, board.results, board.profile
    seeds = sorted(set(results["seed"]))
    protocol = ", ".join(sorted(set(results["protocol"])))
    provenance = "\n".join(
        f"| {key} | {', '.join(values)} |" for key, values in _provenance(results).items()
    )
    cells = "\n".join(
        f"![{name}](figures/{name}.png)"
        for name in board.figure_names
        if name.startswith("trajectory-")
    )
    link = board.results_link
    banner = f"\n{SMOKE_BANNER.format(profile=profile)}\n" if board.smoke else ""
    omitted = SMOKE_OMITTED.format(profile=profile)
    comparison = omitted if board.smoke else paper_comparison(summary)
    tested = (
        omitted if board.smoke else f"{FINDINGS_GUIDE}\n\n{findings.findings_markdown(summary)}"
    )
    return f"""# Leaderboard: profile `{profile}`, protocol {protocol}
{banner}
Written by `kkl-bench publish` from the results in [`{link}/`]({link}/)
alone; every number here is in those files. [`index.html`](index.html) is the
same leaderboard as a page (sortable, filterable; open it from disk).

## How to read it

{board.guide}

## RMSE (SMAPE %) per system and input regime

{render(summary, "markdown")}
## Our RMSE over the paper's

Each of the paper's four methods against our row of the same name (`static_hyperkkl`
is the paper's observer, gain 1; our guarded variant is `static_hyperkkl[guard=True]`).
Below 1: ours is lower. The paper's numbers come from its own test sets.

{comparison}

## The paper's findings, re-tested

{tested}

## Relative to the UKF

![RMSE relative to the UKF](figures/relative-rmse.png)
{_limit_markdown(summary)}
## Cost, training budget and map quality

Means over regimes and seeds. Phase 1 (rate selection, encoder `T`, decoder
`T*`) is trained once per system and seed and shared by every KKL row; its
steps and samples are counted in every KKL row but spent once. The second
phase is the estimator's own training (hypernetwork, injection network,
curriculum or decoder adaptation). A *sample* is one example a loss
evaluates (a state-latent pair, a PDE collocation point, an input window
with its state). Fit times are the wall times of each fit where it ran
(they depend on the machine and on how many jobs ran beside it). Trained
networks are cached and shared: Phase 1 counts in the fit time of the first
KKL estimator that trained it, and a variant that changes only how trained
networks are used online (such as `[guard=True]`) shows only the time to load
them; a fit resumed from its checkpoints after an interruption shows only
the time since it resumed. {_cost_source(board.costs)}

{cost_table(summary)}
{_measured_cost_markdown(board.costs)}
![Estimation cost against RMSE](figures/cost-accuracy.png)

## Test trajectory 0 of every cell

Each state's truth (black) and every estimator's estimate (first seed), and
below them the estimation-error norm on a log scale.

{cells}

{_tracks_markdown(board.tables, board.figure_names, board.scaling_study)}## Provenance

| what | value |
|---|---|
| seeds | {", ".join(map(str, seeds))} |
{provenance}

## Reproduce

{RUNS_TEXT}

{_runs_markdown(board.runs)}
"""


_PAGE_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5rem auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; font-size: 0.85rem; margin: 0.5rem 0 1.5rem; }
th, td { border-bottom: 1px solid #ddd; padding: 0.25rem 0.5rem; text-align: right; }
th { background: #f4f4f4; cursor: pointer; user-select: none; position: sticky; top: 0; }
th.sorted-asc::after { content: " \\25B2"; } th.sorted-desc::after { content: " \\25BC"; }
td.text, th.text { text-align: left; white-space: pre-line; }
td.best { font-weight: bold; } td.tied { font-style: italic; }
.controls label { margin-right: 1rem; } img { max-width: 100%; }
pre { background: #f4f4f4; padding: 0.6rem; overflow-x: auto; }
"""

_PAGE_SCRIPT = """
function sortTable(header) {
  const table = header.closest("table");
  const body = table.tBodies[0];
  const index = Array.from(header.parentNode.children).indexOf(header);
  const ascending = !header.classList.contains("sorted-asc");
  table.querySelectorAll("th").forEach(th => th.classList.remove("sorted-asc", "sorted-desc"));
  header.classList.add(ascending ? "sorted-asc" : "sorted-desc");
  const key = row => {
    const cell = row.children[index];
    const value = cell.dataset.value !== undefined ? cell.dataset.value : cell.textContent;
    const number = parseFloat(value);
    return isNaN(number) ? value : number;
  };
  const rows = Array.from(body.rows);
  rows.sort((a, b) => {
    const x = key(a), y = key(b);
    if (typeof x === "number" && typeof y === "number") return ascending ? x - y : y - x;
    return ascending ? String(x).localeCompare(String(y)) : String(y).localeCompare(String(x));
  });
  rows.forEach(row => body.appendChild(row));
}
function applyFilters() {
  const system = document.getElementById("filter-system").value;
  const regime = document.getElementById("filter-regime").value;
  document.querySelectorAll("tr[data-system]").forEach(row => {
    const show = (!system || row.dataset.system === system) &&
                 (!regime || !row.dataset.regime || row.dataset.regime === regime);
    row.hidden = !show;
  });
  document.querySelectorAll("figure[data-system]").forEach(figure => {
    figure.hidden = (system && figure.dataset.system !== system) ||
                    (regime && figure.dataset.regime !== regime);
  });
}
document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("table.sortable th").forEach(th =>
    th.addEventListener("click", () => sortTable(th)));
  document.getElementById("filter-system").addEventListener("change", applyFilters);
  document.getElementById("filter-regime").addEventListener("change", applyFilters);
});
"""


def _number(value) -> str:
    """A ``data-value`` attribute for sorting: numbers as they are, missing as +inf."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "Infinity"
    return repr(float(value))


def _inline_markdown(text: str) -> str:
    """The inline Markdown the reading guide uses (`code`, **bold**, *italics*, [links](to))
    as HTML."""
    text = re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", r'<a href="\2">\1</a>', text)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    text = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", text)
    return re.sub(r"\*([^*]+)\*", r"<em>\1</em>", text)


def _html_table(
    frame: pd.DataFrame, columns: dict[str, str], table_id: str, mark: pd.Series | None = None
) -> str:
    """A sortable table; rows carry ``data-system`` / ``data-regime`` for the filters."""
    kinds = {c: "num" if pd.api.types.is_numeric_dtype(frame[c]) else "text" for c in columns}
    head = "".join(f'<th class="{kinds[c]}">{html.escape(t)}</th>' for c, t in columns.items())
    rows = []
    for index, row in frame.iterrows():
        attributes = "".join(
            f' data-{key}="{html.escape(str(row[key]))}"'
            for key in ("system", "regime")
            if key in frame
        )
        cells = []
        for column in columns:
            value = row[column]
            css = kinds[column]
            if column == "rmse_mean" and mark is not None and mark[index]:
                css += f" {mark[index]}"
            if isinstance(value, float | int) and not isinstance(value, bool):
                text = "" if isinstance(value, float) and math.isnan(value) else f"{value:.4g}"
                cells.append(f'<td class="{css}" data-value="{_number(value)}">{text}</td>')
            else:
                cells.append(f'<td class="{css}">{html.escape(str(value))}</td>')
        rows.append(f"<tr{attributes}>{''.join(cells)}</tr>")
    return (
        f'<table class="sortable" id="{table_id}"><thead><tr>{head}</tr></thead>'
        f"<tbody>\n{chr(10).join(rows)}\n</tbody></table>"
    )


RESULT_COLUMNS = {
    "estimator": "Estimator",
    "system": "System",
    "regime": "Regime",
    "n_seeds": "Seeds",
    "rmse_mean": "RMSE",
    "rmse_seed_std": "± std over seeds",
    "smape_mean": "SMAPE %",
    "n_diverged": "Diverged",
    "relative": "RMSE / UKF",
    "estimate_us_per_step": "µs / trajectory-step",
    "mark": "Mark",
}
"""The page's result-table columns."""
SETTLING_COLUMNS = {"settling_median_s": "Settling (s, median)", "n_unsettled": "Never settled"}


def _ours_with_relative(summary: pd.DataFrame) -> pd.DataFrame:
    """Our rows of ``summary`` with ``relative``: RMSE over the reference filter's, per cell."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)].copy()
    reference = ours[ours["estimator"] == figures.REFERENCE].set_index(["system", "regime"])[
        "rmse_mean"
    ]
    ours["relative"] = [
        row.rmse_mean / reference.get((row.system, row.regime), math.nan)
        for row in ours.itertuples()
    ]
    return ours


RATIO_COLUMNS = {
    "ratio": "RMSE / paper-track RMSE",
    "n_diverged": "Diverged",
    "n_trajectories": "Trajectories",
}
"""The page's columns of a :func:`track_summary` frame, after its keys."""


def _tracks_html(tables: TrackTables, figure_names: list[str]) -> str:
    """The page's section of the tracks other than the paper's (empty if there are none)."""
    if not tables.summaries:
        return ""
    parts = [
        "<h2>Tracks</h2>",
        "<p>Each estimator fitted once as for the paper track and scored on every track "
        "(a <code>+logged</code> row: fitted again per true plant of <code>mismatch</code>). "
        "Geometric mean over a track's cells of the RMSE over the estimator's own "
        "paper-track RMSE (same system, the task's reference regime; see the README).</p>",
        _html_table(
            tables.relative,
            {"estimator": "Estimator", "track": "Track", **RATIO_COLUMNS},
            "tracks",
        ),
    ]
    for name, summary in tables.summaries.items():
        ours = _ours_with_relative(summary)
        columns = dict(RESULT_COLUMNS)
        if _settling(name):
            columns.update(SETTLING_COLUMNS)
        track = find_track(name)
        grouped = _grouped_conditions(tables.conditions, name)
        parts += [
            f"<h3>Track <code>{html.escape(name)}</code></h3>",
            f"<p>{html.escape(track.description)}</p>" if track else "",
            _html_table(ours, columns, f"track-{name}", ours["mark"]),
            *(
                [
                    f"<p>{html.escape(CONDITIONS_TEXT)}</p>",
                    _html_table(
                        grouped,
                        {"estimator": "Estimator", "condition": "Condition", **RATIO_COLUMNS},
                        f"track-{name}-conditions",
                    ),
                ]
                if grouped is not None
                else []
            ),
            f'<figure><img src="figures/relative-rmse-{name}.svg" '
            f'alt="{html.escape(name)}: RMSE relative to the UKF"></figure>',
            *(
                f'<figure><img src="figures/{figure}.svg" alt="{figure}"></figure>'
                for figure in figure_names
                if figure.startswith(f"track-{name}-")
            ),
        ]
    return "\n".join(parts)


FINDINGS_GUIDE = """Each claim below is tested cell by cell on the results above: the ratio is
the first estimator's RMSE over the second's (means over seeds), with its 90 %
interval from the paired hierarchical bootstrap of the marks. A cell
*supports* the claim when the interval lies below 1 (a one-sided test at 5 %),
*contradicts* it when it lies above 1, and is *undecided* otherwise.
`static_hyperkkl` is the paper's observer (unguarded); the zero input is left
out of the hypernetwork claims, where a hypernetwork equals the autonomous
observer by construction. `kkl_bench/findings.py` states the claims."""

FINDING_COLUMNS = {
    "system": "System",
    "regime": "Regime",
    "rmse_a": "RMSE (claimed lower)",
    "rmse_b": "RMSE (claimed higher)",
    "ratio": "Ratio",
    "low": "90 % low",
    "high": "90 % high",
    "outcome": "Claim",
}


def _findings_html(summary: pd.DataFrame) -> str:
    parts = [
        f"<h2>The paper's findings, re-tested</h2>\n<p>{_inline_markdown(html.escape(FINDINGS_GUIDE))}</p>"
    ]
    for number, finding, claims in findings.tested(summary):
        parts.append(
            f"<h3>{html.escape(finding.title)}</h3>\n"
            f"<p>The paper: &ldquo;{html.escape(finding.paper)}&rdquo;.</p>"
        )
        for index, (claim, frame) in enumerate(claims):
            parts.append(
                f"<p><code>{html.escape(claim.lower)}</code> lower than "
                f"<code>{html.escape(claim.higher)}</code>: "
                f"<strong>{findings.tally(frame)}</strong>.</p>\n"
                + _html_table(frame, FINDING_COLUMNS, f"finding-{number}-{index}")
            )
    return "\n".join(parts) + "\n"


def _limit_html(summary: pd.DataFrame) -> str:
    frame = limit_frame(summary)
    if frame.empty:
        return ""
    return f"<h2>Distance from the Bayes limit</h2>\n{_html_table(frame, LIMIT_COLUMNS, 'limit')}\n"


RUN_COLUMNS = {
    "estimator": "Row",
    "seeds": "Seeds on tracks",
    "cells": "Cells",
    "commits": "Commits",
    "commands": "Command lines",
}
"""The page's columns of :func:`runs_frame`."""


def _page(board: Board) -> str:
    summary, results, profile = board.summary, board.results, board.profile
    figure_names, tables, costs = board.figure_names, board.tables, board.costs
    ours = _ours_with_relative(summary)
    paper = summary[summary["estimator"].str.startswith(PAPER_PREFIX)]
    paper_columns = {
        "estimator": "Method",
        "system": "System",
        "regime": "Regime",
        "rmse_mean": "RMSE",
        "smape_mean": "SMAPE %",
    }
    cost_rows = cost_frame(summary)
    options = "".join(
        f'<option value="{k}">{html.escape(v)}</option>'
        for k, v in SYSTEM_TITLES.items()
        if k in set(ours["system"])
    )
    regime_options = "".join(
        f'<option value="{k}">{html.escape(v)}</option>'
        for k, v in REGIME_TITLES.items()
        if k in set(ours["regime"])
    )
    trajectory_figures = "\n".join(
        f'<figure data-system="{name.split("-")[1]}" data-regime="{name.split("-")[2]}">'
        f'<img src="figures/{name}.svg" alt="{name}"></figure>'
        for name in figure_names
        if name.startswith("trajectory-")
    )
    provenance = "".join(
        f"<tr><td class='text'>{html.escape(k)}</td><td class='text'>{html.escape(', '.join(v))}</td></tr>"
        for k, v in _provenance(results).items()
    )
    runs = board.runs.assign(commands=board.runs["commands"].map("\n".join))
    guide = _inline_markdown(html.escape(board.guide)).replace("\n\n", "</p><p>")
    banner = (
        f"<p>{_inline_markdown(html.escape(SMOKE_BANNER.format(profile=profile)))}</p>\n"
        if board.smoke
        else ""
    )
    tested = (
        f"<h2>The paper's findings, re-tested</h2>\n"
        f"<p>{_inline_markdown(html.escape(SMOKE_OMITTED.format(profile=profile)))}</p>\n"
        if board.smoke
        else _findings_html(summary)
    )
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>kkl-bench leaderboard ({html.escape(profile)})</title>
<style>{_PAGE_STYLE}</style>
<script>{_PAGE_SCRIPT}</script>
</head>
<body>
<h1>kkl-bench leaderboard: profile <code>{html.escape(profile)}</code></h1>
{banner}<p>{guide}</p>
<p>Click a column header to sort; choose a system or a regime to filter.</p>
<div class="controls">
<label>System <select id="filter-system"><option value="">all</option>{options}</select></label>
<label>Regime <select id="filter-regime"><option value="">all</option>{regime_options}</select></label>
</div>
<h2>Results</h2>
{_html_table(ours, RESULT_COLUMNS, "results", ours["mark"])}
<h2>The paper's numbers</h2>
{_html_table(paper, paper_columns, "paper")}
{tested}{_limit_html(summary)}<h2>Cost, training budget and map quality</h2>
<p>{_inline_markdown(html.escape(_cost_source(costs)))}</p>
{_html_table(cost_rows, {"estimator": "Estimator", "system": "System", **COST_COLUMNS}, "costs")}
<h2>Figures</h2>
<figure><img src="figures/relative-rmse.svg" alt="RMSE relative to the UKF"></figure>
<figure><img src="figures/cost-accuracy.svg" alt="estimation cost against RMSE"></figure>
{trajectory_figures}
{_tracks_html(tables, figure_names)}
<h2>Provenance</h2>
<table><tbody>{provenance}</tbody></table>
<h2>Reproduce</h2>
<p>{_inline_markdown(html.escape(RUNS_TEXT))}</p>
{_html_table(runs, RUN_COLUMNS, "runs")}
</body>
</html>
"""


def draw_figures(
    summary: pd.DataFrame,
    results_dir: Path,
    profile: str,
    out: Path,
    tracks: dict[str, pd.DataFrame] | None = None,
) -> list[str]:
    """Draw every figure into ``out/figures`` (PNG and SVG); returns their names.

    ``summary`` is the paper track's; each of ``tracks`` (name -> summary) gets
    its own heat map.
    """
    names = []
    kept = kept_estimates(results_dir, profile)
    directory = out / "figures"
    figures.save(figures.relative_rmse_heatmap(summary), directory / "relative-rmse")
    for name, of_track in (tracks or {}).items():
        heatmap = figures.relative_rmse_heatmap(of_track, f"Track {name}: ")
        figures.save(heatmap, directory / f"relative-rmse-{name}")
        names.append(f"relative-rmse-{name}")
        if _settling(name):  # where the first test trajectory starts matters: draw it
            names += _track_trajectories(name, results_dir, profile, directory)
    figures.save(figures.cost_accuracy_figure(summary), directory / "cost-accuracy")
    names += ["relative-rmse", "cost-accuracy"]
    for system in SYSTEM_TITLES:
        for regime in REGIME_TITLES:
            cell = {e: k for (e, s, r), k in kept.items() if (s, r) == (system, regime)}
            if not cell:
                continue
            name = f"trajectory-{system}-{regime}"
            title = f"{SYSTEM_TITLES[system]}, {regime} input"
            figures.save(figures.trajectory_figure(title, cell), directory / name)
            names.append(name)
    return names


def _track_trajectories(track: str, results_dir: Path, profile: str, directory: Path) -> list[str]:
    """Test trajectory 0 of ``track``'s first task on every system; returns the names drawn."""
    kept = kept_estimates(results_dir, profile, track)
    declared = find_track(track)
    first = declared.task_names()[0] if declared else min(r for _, _, r in kept)
    names = []
    for system in SYSTEM_TITLES:
        cell = {e: k for (e, s, r), k in kept.items() if (s, r) == (system, first)}
        if cell:
            name = f"track-{track}-{system}-{first}"
            title = f"Track {track}: {SYSTEM_TITLES[system]}, {first} input"
            figures.save(figures.trajectory_figure(title, cell), directory / name)
            names.append(name)
    return names


def publish(
    results: pd.DataFrame,
    results_dir: Path,
    out: Path,
    margin: float = MARGIN,
    force: bool = False,
) -> list[Path]:
    """Write the leaderboard folder of ``results`` (one profile's cells, of any tracks, from
    :func:`~kkl_bench.results.load_results` of ``results_dir``) into ``out``.

    ``out`` is owned through its manifest (:data:`MANIFEST`): the files of the previous
    publication that this one does not write are removed, and a folder holding a board of
    another profile or of another results folder, or files no publication recorded, is
    refused (:class:`PublishRefused`) unless ``force``. ``margin`` is the marks'
    practical-equivalence margin. Returns the files written.
    """
    profiles = sorted(set(results["profile"]))
    if len(profiles) != 1:
        raise ValueError(f"publish one profile at a time; the results hold {', '.join(profiles)}")
    profile = profiles[0]
    paper = results[results["track"] == PAPER_TRACK]
    if paper.empty:
        raise ValueError(
            "publishing needs the paper track's cells (every other track is read against "
            "them); run `kkl-bench run` with --track paper"
        )
    link = Path(os.path.relpath(Path(results_dir).resolve(), Path(out).resolve())).as_posix()
    previous = owned_files(out, profile, link, force)
    summary = summary_table(paper, with_paper=True, margin=margin)
    costs = read_costs(out / COST_FILE)
    if costs is not None:
        costs = costs[costs["track"] == PAPER_TRACK]
        summary = with_measured_costs(summary, costs)
    tables = TrackTables.of(results, margin)
    out.mkdir(parents=True, exist_ok=True)
    figure_names = draw_figures(summary, results_dir, profile, out, tables.summaries)
    board = Board(
        summary=summary,
        results=paper,
        profile=profile,
        figure_names=figure_names,
        tables=tables,
        runs=runs_frame(results),
        failed=failed_seeds(paper),
        results_link=link,
        smoke=_is_smoke(profile),
        margin=margin,
        scaling_study=(out / "scaling.md").exists(),
        costs=costs,
    )
    written = {
        "README.md": _markdown(board),
        f"{profile}.tex": render(summary, "latex"),
        f"{profile}.csv": render(
            summary[~summary["estimator"].str.startswith(PAPER_PREFIX)], "csv"
        ),
        "index.html": _page(board),
    }
    for name, track_summary_frame in tables.summaries.items():
        written[f"{profile}-{name}.tex"] = render(
            track_summary_frame, "latex", settling=_settling(name)
        )
        written[f"{profile}-{name}.csv"] = render(track_summary_frame, "csv")
    for name, text in written.items():
        (out / name).write_text(text)
    files = sorted(
        [*written, *(f"figures/{name}.{kind}" for name in figure_names for kind in ("png", "svg"))]
    )
    for stale in sorted(set(previous) - set(files)):
        (out / stale).unlink(missing_ok=True)
    manifest = {"profile": profile, "results": link, "files": files}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return [out / name for name in files]


def _is_smoke(profile: str) -> bool:
    """Whether ``profile`` is a smoke test (False for a profile not installed here)."""
    try:
        return get_profile(profile).smoke
    except ProfileError:
        return False


def owned_files(out: Path, profile: str, link: str, force: bool) -> list[str]:
    """The files (relative to ``out``) of the publication that ``out`` holds, after making
    sure this one may replace it: one of ``profile`` from the results at ``link`` (relative
    to ``out``). Raises :class:`PublishRefused` saying why, and what ``force`` would
    replace, for a board of another profile or results folder, or for a folder with a
    board no publication recorded."""
    manifest_path = out / MANIFEST
    if manifest_path.exists():
        manifest = json.loads(manifest_path.read_text())
        previous, reasons = list(manifest["files"]), []
        if manifest["profile"] != profile:
            reasons.append(f"its board is of profile {manifest['profile']!r} (this is {profile!r})")
        if (out / manifest["results"]).resolve() != (out / link).resolve():
            reasons.append(
                f"its board was made from the results in {out / manifest['results']} (these "
                f"are in {out / link})"
            )
    else:
        previous = [name for name in ("README.md", "index.html") if (out / name).exists()]
        reasons = []
        if previous:
            reasons.append(
                f"its {', '.join(previous)} were not written by `kkl-bench publish` (it has "
                f"no {MANIFEST})"
            )
    if reasons and not force:
        shown = ", ".join(previous[:4]) + (
            f" and {len(previous) - 4} more" if len(previous) > 4 else ""
        )
        raise PublishRefused(
            f"refusing to publish into {out}/: {'; '.join(reasons)}. "
            f"Publish to a new folder (--out), or pass --force to replace its {len(previous)} "
            f"published file(s) ({shown})"
        )
    return previous
