"""The scaling study as a section of text, tables and a figure (``scaling.md``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import pandas as pd

from kkl_bench import families
from kkl_bench.analysis import figures
from kkl_bench.analysis.document import HTML, Figure, Section, Table, Text
from kkl_bench.analysis.scaling import (
    BATCHES,
    ENGINE_ONLINE,
    GROWTHS,
    LOCAL_FILTER,
    MODELS,
    NOT_RUN,
    ONLINE,
    REFERENCE,
    REFERENCE_ONLINE,
    REGIME,
    RMSE_RATIO,
    SPEEDUPS,
    STEPS,
    TRACK,
    cost_against,
    crossover,
    exponents,
    scaling_frame,
    system_name,
    trained_fit_times,
)
from kkl_bench.report import markdown


def study_section(frame: pd.DataFrame, profile: str) -> Section:
    """The study: the per-size table, the exponents and the EKF crossovers."""
    sizes = sorted(set(frame["n"]))
    table = []
    for estimator, rows_of in frame.groupby("estimator"):
        for row in rows_of.itertuples():
            ok = row.status == "ok"
            table.append(
                [
                    estimator,
                    row.n,
                    _rmse(row),
                    _seconds(row.fit_time_s) if ok else "-",
                    row.converged if ok else "-",
                    *(_online(row, batch) for batch in BATCHES),
                    *(_cost(getattr(row, column)) for column in (RMSE_RATIO, *SPEEDUPS)),
                ]
            )
    fitted = exponents(frame)
    runs_of = frame.dropna(subset=["timing_run"]).groupby("estimator")["timing_run"].nunique()
    mixed = set(runs_of[runs_of > 1].index)
    exponent_table = [
        [
            row.estimator,
            *(
                _exponent(getattr(row, column))
                + (" †" if row.estimator in mixed and column in ONLINE else "")
                for column in GROWTHS
            ),
        ]
        for row in fitted.itertuples()
    ]
    compared = [REFERENCE, *([LOCAL_FILTER] if LOCAL_FILTER in set(frame["estimator"]) else [])]
    cheaper = {against: crossover(frame, against) for against in compared}
    crossings = [
        [
            estimator,
            *(
                _crossing(
                    cheaper[against].get((estimator, batch)),
                    _timed_sizes(frame, estimator, batch, against),
                )
                for against in compared
                for batch in BATCHES
            ),
        ]
        for estimator in sorted(set(frame["estimator"]) - {REFERENCE})
    ]
    note = (
        "\n\n† fitted to online costs from more than one timing run: the machine's "
        "speed differs between runs (compare the EKF's costs in each), so the "
        "exponent mixes that drift in."
        if mixed
        else ""
    )
    return Section(
        "",
        [
            Text(
                f"Lorenz-96 at n = {', '.join(map(str, sizes))} (track `{TRACK}`, profile "
                f"`{profile}`). RMSE and fit time: means over the four regimes and the training "
                "seeds. Fit time: the time of every training the fit used, wherever it ran "
                "(processor time on a CPU, wall time on a GPU; protocol section 5) "
                "(stored with each trained model, so a KKL observer's shared Phase 1 counts in "
                "every KKL row; '-' for a model trained before training times were recorded). "
                "Converged: whether every training's validation curve had flattened (protocol "
                "6.5; 'no': a curve still falling, 'diverged': one that ended above twice its "
                "best, 'not recorded': a model trained before the curves were). "
                "Online cost: the fastest of three timed calls on the first "
                f"{STEPS} samples of the `{REGIME}` test trajectories, every estimator timed in "
                f"turn in one run on one thread.{_engines(frame)}{_models(frame)} "
                "RMSE / EKF: the row's RMSE over the EKF's at "
                "the same n; EKF cost / cost: the EKF's µs/step in the row's own timing run over "
                f"the row's (above 1: the row is that many times cheaper).{_later_runs(frame)}"
            ),
            _table(
                table,
                [
                    "Estimator",
                    "n",
                    "RMSE",
                    "Fit time (s)",
                    "Converged",
                    "µs/step, batch 20",
                    "µs/step, batch 1",
                    "RMSE / EKF",
                    "EKF cost / cost, batch 20",
                    "batch 1",
                ],
            ),
            *_unsupported(frame),
            *_not_run(frame, profile),
            Text("Fitted exponents p of value ~ n^p (least squares on log-log):"),
            _table(
                exponent_table,
                ["Estimator", "RMSE", "fit time", "online, batch 20", "online, batch 1"],
            ),
            *([Text(note.strip())] if note else []),
            Text(
                "Where each estimator is cheaper online than the EKF"
                + (f" and than `{LOCAL_FILTER}`" if len(compared) > 1 else "")
                + " timed in the same run (sizes measured by both):"
            ),
            _table(
                crossings,
                [
                    "Estimator",
                    *(
                        f"than {'the EKF' if against == REFERENCE else f'`{against}`'}, "
                        f"batch {batch}"
                        for against in compared
                        for batch in BATCHES
                    ),
                ],
            ),
            Figure("scaling", "scaling"),
        ],
    )


def _table(rows: list[list], headers: list[str]) -> Table:
    """A table of texts (numbers already written)."""
    keys = [f"c{i}" for i in range(len(headers))]
    frame = pd.DataFrame([[str(cell) for cell in row] for row in rows], columns=keys)
    return Table(frame, dict(zip(keys, headers, strict=True)))


def _later_runs(frame: pd.DataFrame) -> str:
    """A sentence per timing run after the first: what it timed, and the reference's costs
    in it beside those of the run that timed the reference's own rows."""
    runs = sorted(int(run) for run in frame["timing_run"].dropna().unique())
    reference = frame[frame["estimator"] == REFERENCE].set_index("n")
    sentences = []
    for run in runs[1:]:
        rows = frame[frame["timing_run"] == run]
        timed = "; ".join(
            f"`{estimator}` at n = {', '.join(map(str, sorted(of['n'])))}"
            for estimator, of in rows.groupby("estimator")
        )
        costs = ", ".join(
            f"n = {row.n}: {_cost(getattr(row, REFERENCE_ONLINE[0]))} and "
            f"{_cost(getattr(row, REFERENCE_ONLINE[1]))} µs/step at batch "
            f"{BATCHES[0]} and {BATCHES[1]}{_stored_reference(reference, row.n, run)}"
            for row in rows.drop_duplicates("n").sort_values("n").itertuples()
        )
        commit = rows["timing_commit"].iloc[0]
        code = f" (code of commit {commit})" if isinstance(commit, str) else ""
        sentences.append(
            f" Timing run {run}{code} added {timed}, beside the {REFERENCE.upper()} at the same "
            f"sizes ({REFERENCE.upper()} in run {run}: {costs})."
        )
    return "".join(sentences)


def _stored_reference(reference: pd.DataFrame, n: int, run: int) -> str:
    """The reference's own costs at ``n`` in brackets, with the run that timed them, unless
    that is ``run`` itself (then they are the costs just given)."""
    stored_run = int(reference.loc[n, "timing_run"])
    if stored_run == run:
        return ""
    costs = " and ".join(_cost(reference.loc[n, column]) for column in ONLINE)
    return f" (run {stored_run}: {costs})"


def _models(frame: pd.DataFrame) -> str:
    """Which timing runs timed untrained models (:data:`~kkl_bench.analysis.scaling.MODELS`), read
    from the timings; nothing for a study of trained models only."""
    if "models" not in frame:
        return ""
    untrained = frame[(frame["models"] == MODELS[1]) & (families.of_rows(frame) == "learned")]
    if untrained.empty:
        return ""
    runs = sorted(set(untrained["timing_run"].astype(int)))
    return (
        f" The learned rows of timing run{'s' if len(runs) > 1 else ''} "
        f"{', '.join(map(str, runs))} were timed on untrained models: built at the profile's "
        "sizes with their trainings cut short and given the published fits' choices made "
        "from data (the injection gain), so they run the trained models' arithmetic, not "
        "their weights (protocol 8)."
    )


def _engines(frame: pd.DataFrame) -> str:
    """What the study's rows with two engines were timed on, read from their timings."""
    if "engine" not in frame:  # a study timed before engines were
        return ""
    compiled = frame[frame["engine"] == "compiled"]
    if compiled.empty:
        return ""
    reference = compiled[compiled["estimator"] == REFERENCE]
    compared = (
        f" The {REFERENCE.upper()} every row is compared with ran its compiled engine at n = "
        f"{', '.join(map(str, sorted(reference['n'])))}."
        if len(reference)
        else ""
    )
    return (
        f" {', '.join(f'`{name}`' for name in sorted(set(compiled['estimator'])))}: timed on "
        "the compiled engine, the reference engine's cost beside it in brackets (protocol "
        f"6.3).{compared}"
    )


def _online(row, batch: int) -> str:
    """A row's online cost at ``batch``; a row timed on its compiled engine gives its
    reference engine's beside it (``0.41 (reference 2046)``)."""
    column = ONLINE[BATCHES.index(batch)]
    cost = _cost(getattr(row, column))
    beside = getattr(row, ENGINE_ONLINE[BATCHES.index(batch)], math.nan)
    return cost if pd.isna(beside) else f"{cost} (reference {_cost(beside)})"


def _rmse(row) -> str:
    """A size's RMSE cell: the RMSE, ``unsupported`` (reasons under the table), ``not run``
    (commands under the table) or the failure's last line."""
    if row.status == "ok":
        return f"{row.rmse:.3g}"
    if row.status in ("unsupported", NOT_RUN):
        return row.status
    return f"failed: {row.reason[:120]}"


def _unsupported(frame: pd.DataFrame) -> list[Text]:
    """Each reason an estimator gave for refusing sizes, with the sizes."""
    refused = frame[frame["status"] == "unsupported"]
    groups = sorted(
        (estimator, sorted(rows_of["n"]), reason)
        for (estimator, reason), rows_of in refused.groupby(["estimator", "reason"])
    )
    lines = [
        f"- `{estimator}` at n = {', '.join(map(str, sizes))}: {reason}"
        for estimator, sizes, reason in groups
    ]
    return [Text("Unsupported (no fit, no number):\n\n" + "\n".join(lines))] if lines else []


def _not_run(frame: pd.DataFrame, profile: str) -> list[Text]:
    """The sizes each estimator lacks results at, with the command that makes them."""
    missing = frame[frame["status"] == NOT_RUN].sort_values(["estimator", "n"])
    lines = [
        f"- `{row.estimator}` at n = {row.n}: {row.reason}; `kkl-bench run --estimator "
        f'"{row.estimator}" --track {TRACK} --profile {profile} --system {system_name(row.n)}'
        f"{' --force' if row.overwrite else ''}`"
        for row in missing.itertuples()
    ]
    heading = "Not run yet (the command that makes the missing cells):"
    return [Text(heading + "\n\n" + "\n".join(lines))] if lines else []


def _cost(value: float) -> str:
    return f"{value:.3g}" if isinstance(value, float) and math.isfinite(value) else "-"


def _seconds(value: float) -> str:
    """A fit time in whole seconds (a filter's fraction of a second reads 0), as the
    board's cost table writes it."""
    return f"{value:,.0f}" if isinstance(value, float) and math.isfinite(value) else "-"


def _exponent(value: float) -> str:
    return f"{round(value, 2) + 0.0:.2f}" if math.isfinite(value) else "-"  # no "-0.00"


def _timed_sizes(frame: pd.DataFrame, estimator: str, batch: int, against: str) -> list[int]:
    """The sizes at which ``estimator``'s online cost at ``batch`` was measured, and
    ``against``'s in the same run (:func:`~kkl_bench.analysis.scaling.cost_against`), ascending."""
    column = ONLINE[BATCHES.index(batch)]
    timed = frame[column].notna() & cost_against(frame, against, batch).notna()
    return sorted(int(n) for n in frame.loc[timed & (frame["estimator"] == estimator), "n"])


def _crossing(cheaper: list[int] | None, timed: Sequence[int]) -> str:
    if not timed or cheaper is None:
        return "not timed"
    if not cheaper:
        return f"never up to n = {max(timed)}"
    return "every n timed" if cheaper == list(timed) else "n = " + ", ".join(map(str, cheaper))


def curves_section(curves: pd.DataFrame) -> Section:
    """The validation curves behind the Converged column."""
    return Section(
        "",
        [
            Text(
                "Validation curves of the fits above (protocol 6.5; the seed timed), "
                "against the share of each training's steps: a row converged where its "
                "curves had flattened before the budget ran out. Fits trained before the "
                "curves were recorded have none."
            ),
            Figure(CURVES_FIGURE, "validation curves"),
        ],
    )


STUDY_FILE, CURVES_FIGURE = "scaling.csv", "scaling-curves"
"""The study's table as ``kkl-bench scaling`` writes it, and its curves' figure."""
TAB = "scaling"
"""The page's panel of the study."""


def study_panel(out: Path, profile: str) -> Section | None:
    """The study in ``out`` (its :data:`STUDY_FILE` and figures, as ``kkl-bench scaling``
    wrote them) as the page's panel :data:`TAB`, or None if ``out`` holds no study."""
    study = Path(out) / STUDY_FILE
    if not study.exists():
        return None
    frame = pd.read_csv(study)
    sizes = sorted(set(frame["n"]))
    blocks = list(study_section(frame, profile).blocks)
    if (Path(out) / "figures" / f"{CURVES_FIGURE}.svg").exists():
        blocks.append(Figure(CURVES_FIGURE, "validation curves of the fits"))
    return Section(
        f"Scaling study: Lorenz-96 from {sizes[0]} to {sizes[-1]} states",
        [replace(block, only=HTML) for block in blocks],
        level=3,
        tab=TAB,
    )


def write_study(
    cells: pd.DataFrame,
    timings: pd.DataFrame,
    profile: str,
    out: Path,
    curves: pd.DataFrame | None = None,
) -> list[Path]:
    """Write ``scaling.md``, ``scaling.csv`` and ``figures/scaling.{png,svg}`` into ``out``,
    and ``figures/scaling-curves.{png,svg}`` if ``curves``
    (:func:`~kkl_bench.analysis.scaling.curve_frame`) holds any."""
    frame = scaling_frame(cells, timings)
    out.mkdir(parents=True, exist_ok=True)
    written_by = Section(
        "", [Text("Written by `kkl-bench scaling` (see `docs/protocol.md` section 8).")]
    )
    has_curves = curves is not None and not curves.empty
    sizes = sorted(set(frame["n"]))
    text = markdown.document(
        f"Scaling study: Lorenz-96 from {sizes[0]} to {sizes[-1]} states",
        [
            written_by,
            study_section(frame, profile),
            *([curves_section(curves)] if has_curves else []),
        ],
    )
    study = out / "scaling.md"
    study.write_text(text, encoding="utf-8")
    table = out / STUDY_FILE
    frame.to_csv(table, index=False, float_format="%.6g")
    plotted = frame.assign(fit_time_s=trained_fit_times(frame))  # a filter's is noise
    figures.save(figures.scaling_figure(plotted, GROWTHS), out / "figures" / "scaling")
    written = [study, table, out / "figures" / "scaling.png"]
    if has_curves:
        figures.save(figures.curves_figure(curves), out / "figures" / CURVES_FIGURE)
        written.append(out / "figures" / f"{CURVES_FIGURE}.png")
    return written
