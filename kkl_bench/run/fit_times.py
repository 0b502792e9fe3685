"""How long a run will take, from the fits recorded before it (``kkl-bench run``'s estimate).

A cell records how long its fit trained (``fit_report.spent``: the seconds stored with
the models, data simulation included; ``fit_time_s`` for a fit that trains nothing) and
how long it was scored (``estimate_us_per_step``). :func:`measure` reduces cells to one
row per (profile, row, system): the median over fits of the training seconds and of
the scoring seconds per cell. The package ships such a table (:data:`SHIPPED`, made by
``kkl-bench fit-times`` from runs on the project's reference machine, one thread a
job); a run's estimate reads the fits recorded in its own results folder first, then
that table. A fit with no record on its profile has no estimate, and the run says so.
"""

from __future__ import annotations

import importlib.resources
import io
import math
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from kkl_bench.protocol import N_SAMPLES
from kkl_bench.run.results import fit_seconds, load_results

SHIPPED = "fit-times.csv"
KEY = ["profile", "estimator", "system"]
COLUMNS = [*KEY, "fit_s", "score_s_per_cell", "fits", "scored_at"]
"""Per key: the median training seconds of its fits, the median scoring seconds per cell,
how many fits, and the commits that scored the cells measured (their provenance)."""


def measure(results: pd.DataFrame) -> pd.DataFrame:
    """One row per (profile, row, system) of ``results``' cells: the median over fits
    (seeds) of the training seconds, and the median scoring seconds per cell."""
    cells = results[results["status"] == "ok"].copy() if not results.empty else results
    if cells.empty:
        return pd.DataFrame(columns=COLUMNS)
    cells["train_s"] = list(map(fit_seconds, cells["fit_report"], cells["fit_time_s"]))
    cells["score_s"] = cells["estimate_us_per_step"] * 1e-6 * cells["n_test"] * N_SAMPLES
    cells["commit"] = [str(record.get("git_commit")) for record in cells["provenance"]]
    fits = cells.groupby([*KEY, "seed"], sort=False).agg(
        train_s=("train_s", "first"), score_s=("score_s", "median"), commit=("commit", "first")
    )
    table = fits.groupby(level=KEY, sort=False).agg(
        fit_s=("train_s", "median"),
        score_s_per_cell=("score_s", "median"),
        fits=("train_s", "size"),
        scored_at=("commit", lambda commits: " ".join(sorted(set(commits)))),
    )
    return table.reset_index()[COLUMNS]


def shipped() -> pd.DataFrame:
    """The fit times the package ships (:data:`SHIPPED`)."""
    source = importlib.resources.files("kkl_bench").joinpath(SHIPPED)
    if not source.is_file():
        return pd.DataFrame(columns=COLUMNS)
    return pd.read_csv(io.StringIO(source.read_text()))


def known(results_dir: Path | None, profile: str) -> pd.DataFrame:
    """The fit times a run on ``profile`` can estimate from: those measured from that
    profile's cells in ``results_dir`` (this machine's own), then the shipped ones for
    what those lack."""
    local = pd.DataFrame(columns=COLUMNS)
    if results_dir is not None and Path(results_dir).is_dir():
        local = measure(load_results(results_dir, damaged=[], profile=profile))
    frames = [frame for frame in (local, shipped()) if not frame.empty]
    both = pd.concat(frames) if frames else pd.DataFrame(columns=COLUMNS)
    return both.drop_duplicates(KEY, keep="first").set_index(KEY)


def estimate(
    fits: Iterable[tuple[str, str, int]], profile: str, table: pd.DataFrame
) -> tuple[list[float], list[str]]:
    """The estimated seconds of each fit ``(row, system, cells)`` on ``profile`` (NaN
    where ``table``, from :func:`known`, has no record) and the ``row on system`` pairs
    without one."""
    seconds, unknown = [], []
    for row, system, cells in fits:
        key = (profile, row, system)
        if key in table.index:
            record = table.loc[key]
            seconds.append(float(record["fit_s"] + cells * record["score_s_per_cell"]))
        else:
            seconds.append(math.nan)
            unknown.append(f"{row} on {system}")
    return seconds, unknown


def merge_into(path: Path, measured: pd.DataFrame) -> pd.DataFrame:
    """``measured`` merged into the CSV at ``path`` (its rows replace those of the same
    key), written; returns the table."""
    frames = [measured] + ([pd.read_csv(path)] if Path(path).exists() else [])
    table = pd.concat(frames).drop_duplicates(KEY, keep="first")
    table = table.sort_values(KEY).reset_index(drop=True)
    Path(path).write_text(table.to_csv(index=False, float_format="%.4g"))
    return table
