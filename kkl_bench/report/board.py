"""What one publication shows (:class:`Board`), and the sections of the paper track."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import pandas as pd

from kkl_bench import families, variants
from kkl_bench.analysis import figures, findings, trainings
from kkl_bench.analysis.comparisons import comparison_cells, limit_table, one_line_answer
from kkl_bench.analysis.cost import COST_FILE
from kkl_bench.analysis.document import HTML, Figure, Section, Table, Text
from kkl_bench.analysis.leaderboard import (
    cost_table,
    grid_tables,
    measured_cost_table,
    paper_comparison,
)
from kkl_bench.analysis.summary import (
    PAPER_PREFIX,
    SYSTEM_TITLES,
    relative_summary,
    summary_table,
    unsupported_reasons,
)
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.registry import estimators

TAB = PAPER_TRACK
"""The page's panel of the paper track."""


@dataclass(frozen=True)
class TrackTables:
    """What the folder shows of the tracks other than the paper's.

    summaries: track name -> its :func:`summary_table`; relative:
    :func:`~kkl_bench.analysis.summary.track_summary` (each track against the paper track);
    conditions: the same by condition; cells: track name -> its cells.
    """

    summaries: dict[str, pd.DataFrame]
    relative: pd.DataFrame
    conditions: pd.DataFrame
    cells: dict[str, pd.DataFrame]

    @classmethod
    def of(
        cls, results: pd.DataFrame, margin: float, paper_summary: pd.DataFrame | None = None
    ) -> TrackTables:
        """The tables of ``results`` (every track's cells); ``paper_summary``, if given, is
        the paper track's :func:`summary_table` at ``margin``, already computed."""
        tracks = dict(iter(results.groupby("track", sort=False)))  # in order of appearance
        summaries = {
            name: paper_summary
            if name == PAPER_TRACK and paper_summary is not None
            else summary_table(of, margin=margin)
            for name, of in tracks.items()
        }
        cells = {name: tracks[name] for name in sorted(tracks) if name != PAPER_TRACK}
        if not cells:
            return cls({}, pd.DataFrame(), pd.DataFrame(), {})
        return cls(
            {name: summaries[name] for name in cells},
            relative_summary(summaries),
            relative_summary(summaries, by_condition=True),
            cells,
        )


@dataclass(frozen=True)
class Board:
    """Everything one publication shows, read from the results once for both renderings.

    summary: the paper track's :func:`summary_table` with the paper's rows; results: the
    paper track's cells; runs: :func:`~kkl_bench.report.provenance.runs_frame` of every
    track's cells; failed: row -> the seeds with a failed paper-track cell; results_link:
    the results folder relative to the published one; smoke: the profile is a smoke test
    (no findings, no ratios to the paper); margin: the marks' practical-equivalence margin;
    scaling_study: ``scaling.md`` stands beside the board; costs: the paper track's rows of
    its ``cost.csv``, if any; verifications: the rows of its ``verification.csv``
    (:mod:`kkl_bench.run.verification`), if any; scaling_panel: the scaling study's panel
    (:func:`kkl_bench.report.scaling.study_panel`), if the folder holds the study;
    every_cell: the cells of every track (what the Reproduce section reads); regeneration:
    the summary of the results folder's regeneration ledger
    (:func:`kkl_bench.run.regenerate.ledger_summary`), if one wrote it.
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
    verifications: pd.DataFrame | None = None
    scaling_panel: Section | None = None
    every_cell: pd.DataFrame | None = None
    regeneration: dict | None = None

    @property
    def cells_of_every_track(self) -> pd.DataFrame:
        """``every_cell``, or the paper track's cells where the board was given no others."""
        return self.every_cell if self.every_cell is not None else self.results

    @cached_property
    def paper_trainings(self) -> pd.DataFrame:
        """Every training of the paper track's fits (:func:`trainings.training_records`),
        read once for the cost section and every track's."""
        return trainings.training_records(self.results)


SMOKE_BANNER = (
    "**A smoke test.** Profile `{profile}` runs the whole pipeline on tiny training "
    "budgets and a few test trajectories: its numbers say nothing about the methods. "
    "The paper's findings and the ratios to the paper's numbers are left out."
)
SMOKE_OMITTED = (
    "Left out: profile `{profile}` is a smoke test, whose numbers say nothing about the "
    "methods (publish a `standard` run for this section)."
)


def introduction(board: Board) -> Section:
    """The untitled opening: what the folder is, and the smoke-test warning if it is one."""
    link = board.results_link
    blocks = [Text(SMOKE_BANNER.format(profile=board.profile))] if board.smoke else []
    blocks.append(
        Text(
            f"Written by `kkl-bench publish` from the results in [`{link}/`]({link}/)\n"
            "alone; every number here is in those files. [`index.html`](index.html) is the\n"
            "same leaderboard as a page (sortable, filterable; open it from disk)."
        )
    )
    return Section("", blocks)


def reading_guide(board: Board) -> Section:
    summary, margin, failed = board.summary, board.margin, board.failed
    ours = {e for e in summary["estimator"] if not e.startswith(PAPER_PREFIX)}
    installed = set(estimators.names())  # publishing needs no plugin; those installed say more
    bases = {e: variants.base_name(e) for e in ours}
    single = sorted(
        e for e in ours if bases[e] in installed and not estimators.get(bases[e]).uses_seed
    )
    seeds = int(summary["n_seeds"].max())
    fewer = summary[summary["estimator"].isin(set(ours) - set(single))]
    fewer = fewer.groupby("estimator")["n_seeds"].max()
    fewer = fewer[(fewer > 0) & (fewer < seeds)]  # a row that ran none is unsupported or failed
    short = (
        " Rows that depend on the seed but ran fewer seeds ("
        + ", ".join(f"`{name}`: {int(count)}" for name, count in fewer.items())
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
    text = f"""Each cell reads `RMSE ± std (SMAPE %)`: for every training seed, the mean
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
reference and never marked. `kkl_bench/analysis/significance.py` has
the exact procedure."""
    page = Text(
        "On the page, each track has a panel: its answer in one line and, where a limit was "
        "scored, each cell's distance from it; then its table in the paper's layout, every "
        "RMSE cell coloured by its ratio to the best possible (the particle filter's "
        "Bayes limit, labelled `(limit)`, where it ran, else the column's lowest RMSE; green "
        "at 1, red from 10 on); then the same numbers as a long table to sort and filter, "
        "folded until opened. A table wider than the page says so above it and scrolls "
        "sideways.",
        only=HTML,
    )
    return Section("How to read it", [Text(text), page], folded=True)


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
}
"""The long table's columns."""
SETTLING_COLUMNS = {"settling_median_s": "Settling (s, median)", "n_unsettled": "Never settled"}


def long_table(summary: pd.DataFrame, name: str, settling: bool = False) -> Table:
    """Our rows of ``summary`` one per cell, with each RMSE over the UKF's (page only)."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)].reset_index(drop=True)
    reference = ours[ours["estimator"] == figures.REFERENCE].set_index(["system", "regime"])
    ours["relative"] = [
        figures.over_reference(
            row.rmse_mean, reference["rmse_mean"].get((row.system, row.regime), math.nan)
        )
        for row in ours.itertuples()
    ]
    ours["estimator"] = ours["estimator"].map(families.shown_names(ours))
    columns = RESULT_COLUMNS | (SETTLING_COLUMNS if settling else {})
    marks = pd.DataFrame("", index=ours.index, columns=list(columns))
    marks["rmse_mean"] = ours["mark"]
    folded = f"Every cell, one row per estimator and task ({len(ours)} rows; sortable)"
    return Table(
        ours, columns, id=name, marks=marks, floatfmt=".4g", sortable=True, only=HTML,
        folded=folded,
    )  # fmt: skip


def paper_sections(board: Board) -> list[Section]:
    summary, profile = board.summary, board.profile
    omitted = Text(SMOKE_OMITTED.format(profile=profile))
    answer = one_line_answer(summary)
    sections = [
        Section(
            "RMSE (SMAPE %) per system and input regime",
            [
                *([Text(f"**In one line.** {answer}")] if answer else []),
                *grid_tables(summary, name="board-paper"),
                *unsupported_blocks(board.results),
                long_table(summary, "results"),
            ],
            tab=TAB,
        ),
        Section(
            "Our RMSE over the paper's",
            [
                Text(
                    "Each of the paper's four methods against our row of the same name "
                    "(`static_hyperkkl`\nis the paper's observer, gain 1; our guarded variant "
                    "is `static_hyperkkl[guard=True]`).\nBelow 1: ours is lower. The paper's "
                    "numbers come from its own test sets. What is known of why ours are lower, "
                    "and what was measured (the paper's network sizes), is in `docs/protocol.md` "
                    'section 6, "The board against the paper\'s numbers".'
                ),
                omitted if board.smoke else paper_comparison(summary),
            ],
            tab=TAB,
        ),
        *finding_sections(board),
        Section(
            "Relative to the UKF", [Figure("relative-rmse", "RMSE relative to the UKF")], tab=TAB
        ),
    ]
    limit = limit_table(summary)
    if limit is not None:
        sections.append(
            Section("Distance from the Bayes limit", [Text(LIMIT_TEXT), limit], tab=TAB)
        )
    sections += [cost_section(board), trajectory_section(board)]
    return sections


def unsupported_blocks(cells: pd.DataFrame) -> list[Text]:
    """Why each row of ``cells`` (one track's) reads `unsupported` where it does, one item
    per row and reason (:func:`unsupported_reasons`); nothing where no cell is."""
    reasons = unsupported_reasons(cells)
    if not reasons:
        return []
    items = "\n".join(
        f"- `{row}` on {', '.join(SYSTEM_TITLES.get(s, s) for s in systems)}: {reason}"
        for row, systems, reason in reasons
    )
    return [
        Text(
            "`unsupported`: the estimator cannot be fitted for the task, for the reason it "
            f"gives (no number is scored):\n\n{items}"
        )
    ]


LIMIT_TEXT = """`particle_filter` estimates the posterior mean under the exact model (protocol
section 6.1): no estimator can expect a lower RMSE. Each row divides the
RMSE of the best model-based and of the best learned row (families as each
estimator declares them) by it (1.00: at the limit; a ratio a little below 1 is the
particle filter's own Monte Carlo error)."""

FINDINGS_GUIDE = """Each claim below is tested cell by cell on the results above: the ratio is
the first estimator's RMSE over the second's (means over seeds), with its 90 %
interval from the paired hierarchical bootstrap of the marks. A cell
*supports* the claim when the interval lies below 1 (a one-sided test at 5 %),
*contradicts* it when it lies above 1, and is *undecided* otherwise.
`static_hyperkkl` is the paper's observer (unguarded); the zero input is left
out of the hypernetwork claims, where a hypernetwork equals the autonomous
observer by construction. `kkl_bench/analysis/findings.py` states the claims."""


def finding_sections(board: Board) -> list[Section]:
    """The paper's findings re-tested: a guide, then per finding its claims' cells."""
    if board.smoke:
        omitted = Text(SMOKE_OMITTED.format(profile=board.profile))
        return [Section("The paper's findings, re-tested", [omitted], tab=TAB)]
    sections = [Section("The paper's findings, re-tested", [Text(FINDINGS_GUIDE)], tab=TAB)]
    for number, finding, claims in findings.tested(board.summary):
        blocks: list = [Text(f'The paper: "{finding.paper}".')]
        for index, (claim, frame) in enumerate(claims):
            headers = [
                "Cell",
                f"`{claim.lower}`",
                f"`{claim.higher}`",
                "ratio",
                "90 % interval",
                "claim",
            ]
            blocks += [
                Text(f"`{claim.lower}` lower than `{claim.higher}`: **{findings.tally(frame)}**."),
                comparison_cells(frame, frame["outcome"], headers, id=f"finding-{number}-{index}"),
            ]
        sections.append(Section(finding.title, blocks, level=3, tab=TAB))
    return sections


COST_TEXT = """Means over regimes and seeds. Phase 1 (rate selection, encoder `T`, decoder
`T*`) is trained once per system and seed and shared by every KKL row; its
steps and samples are counted in every KKL row but spent once. The second
phase is the estimator's own training (hypernetwork, injection network,
curriculum or decoder adaptation). A *sample* is one example a loss
evaluates (a state-latent pair, a PDE collocation point, an input window
with its state). Fit times are those of the trainings each fit used, stored
with the trained models (protocol section 5), so a model loaded from the
cache counts as long as it took to train: Phase 1 counts in every KKL row, as
its steps do, and a variant that only uses trained networks differently online
(such as `[guard=True]`) shows the time its networks took. A training on the
CPU counts its processor seconds (one thread a fit, whatever else ran on the
machine), one on a GPU or from before processor times were recorded its wall
seconds, and a fit that trains nothing its wall time; all depend on the
machine. Converged (protocol 6.5, read from each training's
record): `yes` when the plateau rule stopped every training, `no` when one
reached its cap of steps, `diverged` when one's validation error was not
finite; a training from before the rule reads `yes` when its curve had
flattened, `no` when it was still falling as its budget ended, `diverged` when
it ended above twice its best error; `not recorded` for models trained before
the curves were. """


def cost_source(costs: pd.DataFrame | None) -> str:
    """Where the estimation column comes from: ``kkl-bench cost`` runs, or the scoring runs."""
    if costs is None or costs.empty:
        return (
            "Estimation times are the wall times of the runs that scored the cells: "
            "several runs on different commits and machine loads, so rows compare only "
            "roughly (`kkl-bench cost` times them side by side)."
        )
    commits = ", ".join(sorted(set(costs["git_commit"].astype(str))))
    threads = ", ".join(map(str, sorted(set(costs["threads"]))))
    runs = costs["run"].nunique()
    source = (
        f"one `kkl-bench cost` run ([`{COST_FILE}`]({COST_FILE}), commit {commits})"
        if runs == 1
        else f"{runs} `kkl-bench cost` runs ([`{COST_FILE}`]({COST_FILE}), commits {commits}; "
        "each row with the EKF timed in its own run)"
    )
    return (
        f"Estimation times come from {source}: every row's trained models (seed "
        f"{', '.join(map(str, sorted(set(costs['seed']))))}) timed in turn on each test "
        f"set of {', '.join(map(str, sorted(set(costs['trajectories']))))} trajectories, "
        f"{threads} thread(s), best of up to "
        f"{costs['rounds'].max()} timings; rows it did not time show their scoring runs' "
        "wall times."
    )


def cost_finding(costs: pd.DataFrame) -> str:
    """What the measurement says of cost, read from it: each engine's rows over the EKF of
    their own run (the range of the per-row means over systems, with the rows at its
    ends), and how far each engine's rows are from their arithmetic floor. Empty for a
    measurement without engines (before protocol 6.3's floors)."""
    if "engine" not in costs or costs["engine"].isna().all():
        return ""
    rows = costs[(costs["estimator"] != "ekf") & costs["engine"].notna()].copy()
    rows["over_ekf"] = rows["us_per_trajectory_step"] / rows["reference_us_per_trajectory_step"]
    means = {"over_ekf": ("over_ekf", "mean"), "over_floor": ("over_floor", "mean")}
    per_system = rows.groupby(["estimator", "system", "engine"]).agg(**means).reset_index()
    per_row = per_system.groupby(["estimator", "engine"]).agg(**means).reset_index("engine")
    ekf = costs[costs["estimator"] == "ekf"]
    ekf_engine = ", ".join(sorted(set(ekf["engine"].dropna()))) or "compiled"
    parts = [f"Against the EKF timed beside them ({ekf_engine} engine)"]
    for engine, group in per_row.groupby("engine"):
        cheapest, dearest = group["over_ekf"].idxmin(), group["over_ekf"].idxmax()
        floor = group["over_floor"].dropna()
        parts.append(
            f"the {len(group)} row(s) timed on the {engine} engine cost "
            f"{group['over_ekf'].min():.3g} (`{cheapest}`) to {group['over_ekf'].max():.3g} "
            f"(`{dearest}`) times the EKF's per trajectory-step (mean over systems)"
            + (
                f" and run at {floor.min():.3g} to {floor.max():.3g} times their floor"
                if len(floor)
                else " (their flops are not counted yet)"
            )
        )
    ekf_floor = ekf["over_floor"].mean() if "over_floor" in ekf else float("nan")
    return "; ".join(parts) + f"; the EKF itself runs at {ekf_floor:.3g} times its floor. "


def cost_section(board: Board) -> Section:
    blocks: list = [Text(COST_TEXT + cost_source(board.costs)), cost_table(board.summary)]
    said = [
        trainings.converged_by_track(board.cells_of_every_track),
        trainings.capped_sentence(board.paper_trainings),
        trainings.diverged_sentence(board.paper_trainings),
    ]
    blocks += [Text(sentence) for sentence in said if sentence]
    if board.costs is not None and not board.costs.empty:
        blocks += [
            Text(
                "Online cost from the same measurement, per system (mean over regimes), the\n"
                "largest cell, and the EKF's cost over each row's. "
                + cost_finding(board.costs)
                + "A row's floor is its flops per trajectory-step at this machine's peak in "
                "its precision, plus the random numbers and transcendental functions it must "
                "compute at their cost, all measured in the same run (protocol 6.3):"
            ),
            measured_cost_table(board.costs),
        ]
    blocks.append(Figure("cost-accuracy", "Estimation cost against RMSE"))
    return Section("Cost, training budget and map quality", blocks, tab=TAB)


def trajectory_section(board: Board) -> Section:
    drawn = [name for name in board.figure_names if name.startswith("trajectory-")]
    return Section(
        "Test trajectory 0 of every cell",
        [
            Text(
                "Each state's truth (black) and every estimator's estimate (first seed), and\n"
                "below them the estimation-error norm on a log scale."
            ),
            *(
                Figure(name, name, system=name.split("-")[1], regime=name.split("-")[2])
                for name in drawn
            ),
        ],
        tab=TAB,
    )
