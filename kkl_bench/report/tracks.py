"""The sections of the tracks other than the paper's: their summary against the paper
track, then one panel per track."""

from __future__ import annotations

import pandas as pd

from kkl_bench.analysis import trainings
from kkl_bench.analysis.comparisons import (
    calibrated_versus_learned,
    comparison_cells,
    headroom_sentence,
    learned_versus_model_based,
    limit_table,
    one_line_answer,
)
from kkl_bench.analysis.document import Figure, Section, Table, Text
from kkl_bench.analysis.leaderboard import grid_tables, track_summary_table
from kkl_bench.analysis.scaling import TRACK as SCALING_TRACK
from kkl_bench.analysis.summary import SYSTEM_TITLES, condition
from kkl_bench.protocol.metrics import SETTLING_THRESHOLD, SETTLING_WINDOW_S
from kkl_bench.report.board import Board, long_table, unsupported_blocks
from kkl_bench.suite.plants import true_plant
from kkl_bench.suite.tracks import find_track

SUMMARY_TAB = "tracks compared"
"""The page's panel of the cross-track summary."""

INTRODUCTION = """Every estimator is fitted once, exactly as for the paper's track (sensor
noise 0.01, the paper's x0 boxes, its own training inputs), and scored on
each track's test sets as well: the tracks test generalization, never
retraining. The exceptions: a `+logged` row of the `mismatch` track, the
estimator fitted again per true plant with the data logged on it; the
`hard` track, where every estimator is fitted for each task's measurement
model; and `particle_filter+truth`, the particle filter told each task's
noise and initial box, the limit of the `noise` and `far-init` tracks.
Marks and spread read as above."""

RELATIVE = """Per estimator: for every cell of the track, its mean RMSE over the
trajectories that did not diverge, divided by its own paper-track RMSE on
the same system under the regime the track's task names as its reference
(for example a chirp against the paper's sinusoid); the geometric mean of
these ratios over the track's cells, and in parentheses their median (one
system can dominate the mean: `docs/protocol.md` section 7.5 on Lorenz with
its parameters 25 % off). Below 1: better than on the paper track.
Diverged trajectories are left out of the ratio and counted beside it."""

TRACK_LIMIT_TEXT = """Distance from the Bayes limit on this track: the particle filter's RMSE
(`particle_filter+truth` where the tasks' noise or initial box differ from what
the estimators were fitted with; on `hard`, `particle_filter` fitted for each
task, with more particles where doubling 10000 moved the cell by more than 2 %,
protocol section 6.1; the limit row names which) and, per cell, the best
model-based and the best learned row (families as each estimator declares them)
with their RMSE divided by it (1.00: at the limit)."""

CONDITIONS_TEXT = (
    "By condition: the ratio to the estimator's own paper-track RMSE as above, its "
    "geometric mean (and median) taken over the systems and regimes of each condition."
)


def settles(name: str) -> bool:
    """Whether track ``name`` shows settling times."""
    track = find_track(name)
    return track is not None and track.settling


def grouped_conditions(conditions: pd.DataFrame, name: str) -> pd.DataFrame | None:
    """Track ``name``'s rows of ``conditions`` (:func:`track_summary` by condition) if its
    tasks group into fewer conditions than tasks (``mismatch``: ``params10``, ``params25``,
    ``sensor``), else None."""
    track = find_track(name)
    if track is None or conditions.empty:
        return None
    rows = conditions[conditions["track"] == name]
    grouped = 1 < rows["condition"].nunique() < len(track.tasks)
    return rows if grouped else None


def calibration_table(cells: pd.DataFrame, track: str) -> Table | None:
    """Per system and true plant of ``track``: each parameter the ``+logged`` model-based
    rows fitted (:mod:`kkl_bench.fitting.calibration`, from their fit reports) beside the true
    plant's, with the relative error; None if no cell recorded a calibration."""
    declared = find_track(track)
    rows, seen = [], set()
    for cell in cells.sort_values(["system", "regime", "estimator"]).itertuples():
        report = cell.fit_report if isinstance(cell.fit_report, dict) else {}
        if "calibration" not in report or declared is None:
            continue
        plant = declared.task(cell.regime).plant
        if (cell.system, plant) in seen:
            continue
        seen.add((cell.system, plant))
        truth = {
            **true_plant(cell.system, plant, track).params(),
            "sensor_gain": plant.sensor_gain,
            "sensor_offset": plant.sensor_offset,
        }
        for name, fitted in report["calibration"].items():
            off = fitted - truth[name]
            rows.append(
                {
                    "system": SYSTEM_TITLES.get(cell.system, cell.system),
                    "plant": condition(track, cell.regime),
                    "parameter": name,
                    "true": truth[name],
                    "fitted": fitted,
                    "error": 100 * off / truth[name] if truth[name] else off,
                }
            )
    if not rows:
        return None
    columns = {
        "system": "System",
        "plant": "Plant",
        "parameter": "Parameter",
        "true": "True plant",
        "fitted": "Calibrated",
        "error": "Error (% of the true value; absolute where it is 0)",
    }
    return Table(pd.DataFrame(rows), columns, id=f"track-{track}-calibration", floatfmt=".4g")


VERSUS_TEXT = (
    "Calibrate the model and filter, or train a network on the logged data? Per cell, "
    "the calibrated UKF (`ukf+logged`) against the learned `+logged` row with the lowest "
    "RMSE: the ratio of their RMSEs with its 90 % interval from the paired bootstrap of "
    "the marks; *lower* where the interval lies below (calibrated lower) or above "
    "(learned lower) 1, *undecided* otherwise."
)
AGAINST_MODEL_BASED_TEXT = (
    "Can a learned row beat the model-based rows, which are handed the exact model and "
    "built for the task's sensor? Per cell, the learned row with the lowest RMSE against "
    "the model-based row with the lowest (families as each estimator declares them; rows "
    "with a diverged trajectory left out): the ratio of their RMSEs with its 90 % "
    "interval from the paired bootstrap of the marks (trajectories and training seeds "
    "resampled); *lower* where the interval lies below (learned lower) or above "
    "(model-based lower) 1, *undecided* otherwise."
)


def versus_blocks(
    frame: pd.DataFrame, text: str, sides: tuple[str, str], headers: tuple[str, str], id: str
) -> list:
    """A :func:`~kkl_bench.analysis.comparisons.best_against_best` frame as a table with a tally per
    condition: ``sides`` name its two sides in verdicts (``"calibrated"``, ``"learned"``),
    ``headers`` its two RMSE columns."""
    if frame.empty:
        return []
    names = {"a lower": f"{sides[0]} lower", "b lower": f"{sides[1]} lower"}
    verdicts = [names.get(verdict, "undecided") for verdict in frame["verdict"]]
    tallies = "; ".join(
        f"`{name}`: {sides[0]} lower in {(rows['verdict'] == 'a lower').sum()} of "
        f"{len(rows)} cells, {sides[1]} lower in {(rows['verdict'] == 'b lower').sum()}"
        for name, rows in frame.groupby("condition", sort=False)
    )
    cells = [
        f"{cell} (`{a}` against `{b}`)"
        for cell, a, b in zip(frame["cell"], frame["a"], frame["b"], strict=True)
    ]
    table = comparison_cells(
        frame.assign(cell=cells),
        verdicts,
        ["Cell (rows compared)", *headers, "ratio", "90 % interval", "verdict"],
        id=id,
    )
    return [Text(f"{text} By condition: {tallies}."), table]


CALIBRATION_TEXT = (
    "The model-based `+logged` rows filter with the nominal model calibrated on the 100 "
    "logged trajectories (protocol section 7.5): its physical parameters and the sensor's "
    "gain and offset, fitted by least squares without reading the true plant. What they "
    "fitted, beside the true plant's values:"
)


def track_sections(board: Board) -> list[Section]:
    """The summary of every track against the paper track, then a section per track
    (empty if there is no other track)."""
    tables = board.tables
    if not tables.summaries:
        return []
    sections = [
        Section("Tracks: where methods break", [Text(INTRODUCTION)], tab=SUMMARY_TAB),
        Section(
            "Each track relative to the paper track",
            [Text(RELATIVE), track_summary_table(tables.relative, id="tracks")],
            level=3,
            tab=SUMMARY_TAB,
        ),
    ]
    for name, summary in tables.summaries.items():
        sections.append(_track(board, name, summary))
    return sections


def _track(board: Board, name: str, summary: pd.DataFrame) -> Section:
    track = find_track(name)
    description = f"{track.description} " if track else ""
    text = (
        f"{description}Task ids read `{name}/<system>/<task>@v<n>`; `docs/protocol.md` "
        "(sections 7\nand 8) defines every task."
    )
    if settles(name):
        text += (
            f"\n\nBeside each RMSE, `settle (s)` is the median over trajectories of the "
            f"settling time: the start of the first {SETTLING_WINDOW_S:g}-second window "
            f"from which on every window's normalized RMSE (error over the test set's state "
            f"standard deviation) stays below {SETTLING_THRESHOLD:g}; `never` counts the "
            "trajectories that never settle."
        )
    if board.scaling_study and name == SCALING_TRACK:
        text += (
            "\n\nHow each estimator's fit time, online cost and RMSE grow with Lorenz-96's "
            "dimension: the [scaling study](scaling.md) (`kkl-bench scaling`; on the page, "
            "the panel `scaling`)."
        )
    answer = one_line_answer(summary)
    blocks = [Text(f"**In one line.** {answer}")] if answer else []
    limit = limit_table(summary, id=f"limit-{name}")
    if limit is not None:
        blocks += [Text(f"{TRACK_LIMIT_TEXT} {headroom_sentence(summary)}"), limit]
    blocks += [
        Text(text),
        *grid_tables(summary, settles(name), name=f"board-{name}"),
        long_table(summary, f"track-{name}", settles(name)),
    ]
    grouped = grouped_conditions(board.tables.conditions, name)
    if grouped is not None:
        blocks += [
            Text(CONDITIONS_TEXT),
            track_summary_table(grouped, "condition", id=f"track-{name}-conditions"),
        ]
    own = trainings.own_records(
        trainings.training_records(board.tables.cells[name]), board.paper_trainings
    )
    counted = "trainings of this track's fits not shared with the paper track"
    for said in (
        trainings.capped_sentence(own, counted),
        trainings.diverged_sentence(own, counted),
    ):
        if said:
            blocks.append(Text(said))
    blocks += unsupported_blocks(board.tables.cells[name])
    calibrated = calibration_table(board.tables.cells[name], name)
    if calibrated is not None:
        blocks += [
            Text(CALIBRATION_TEXT),
            calibrated,
            *versus_blocks(
                calibrated_versus_learned(summary, name),
                VERSUS_TEXT,
                ("calibrated", "learned"),
                ("RMSE calibrated", "RMSE learned"),
                id=f"track-{name}-versus",
            ),
        ]
    if track is not None and track.fitted_per_task:
        blocks += versus_blocks(
            learned_versus_model_based(summary, name),
            AGAINST_MODEL_BASED_TEXT,
            ("learned", "model-based"),
            ("RMSE learned", "RMSE model-based"),
            id=f"track-{name}-against-filters",
        )
    blocks.append(Figure(f"relative-rmse-{name}", f"{name}: RMSE relative to the UKF"))
    blocks += [
        Figure(figure, figure)
        for figure in board.figure_names
        if figure.startswith(f"track-{name}-")
    ]
    return Section(f"Track `{name}`", blocks, level=3, tab=name)
