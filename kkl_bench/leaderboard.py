"""Leaderboard tables from stored results, in the paper's layout.

Rows are estimators, columns are (system, regime) pairs grouped two systems
per table as in the paper's Tables 1-2. A cell reads ``RMSE ± std (SMAPE %)``:
for each training seed the mean over the test trajectories, then the mean
of those over the seeds, ``±`` their standard deviation over the seeds
(absent for one seed). The ``Seeds`` column says how many. Marks come from
:mod:`kkl_bench.significance`: **bold** where the lowest RMSE beats every
other entry of its column by a paired bootstrap at 5 %, *italic* for the
entries tied with the lowest (not distinguishable from it). A cell where some
trajectory diverged reads ``diverged (k/n), median m`` (over all seeds, with
the median RMSE of all its trajectories); a cell whose estimator failed reads
``error``. Tables show one track at a time (callers select its cells);
tracks that declare it add the settling time beside each RMSE, and
:func:`track_summary` compares each track with the paper track. The paper's
published numbers can be shown as reference rows (never marked: they come
from other test sets). Nothing here recomputes a metric: it reads what the
harness recorded.
"""

from __future__ import annotations

import importlib.resources
import io
import math
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd
from tabulate import tabulate

from kkl_bench import variants
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.results import mean_and_std
from kkl_bench.significance import MARGIN, compare, mark_column
from kkl_bench.tracks import find_track

FORMATS = ("markdown", "latex", "csv")
PAPER_PREFIX = "paper:"
SYSTEM_TITLES = {
    "duffing": "Duffing",
    "vdp": "Van der Pol",
    "rossler": "Rossler",
    "lorenz": "Lorenz",
    "fitzhugh_nagumo": "FitzHugh-Nagumo",
    "chua": "Chua",
    **{f"lorenz96-n{n}": f"Lorenz-96 n={n}" for n in (5, 10, 20, 40)},
}
"""Table and figure titles of the built-in systems, in the order tables show them."""
REGIME_TITLES = {"zero": "Zero", "constant": "Const", "sinusoid": "Sin", "square": "Sqr"}
MARKUP = {
    "markdown": {"best": ("**", "**"), "tied": ("*", "*")},
    "latex": {"best": (r"\textbf{", "}"), "tied": (r"\textit{", "}")},
}


def paper_results() -> pd.DataFrame:
    """The HyperKKL paper's Tables 1-2: columns method, system, regime, rmse, smape_percent."""
    text = importlib.resources.files("kkl_bench").joinpath("paper_results.csv").read_text()
    return pd.read_csv(io.StringIO(text))


def _seed_mean_and_std(per_seed: list[float]) -> tuple[float, float]:
    """Mean over seeds and the standard deviation over seeds (ddof 1; NaN for one seed)."""
    if not per_seed:
        return math.nan, math.nan
    if not all(math.isfinite(value) for value in per_seed):
        return math.inf, math.inf
    values = np.asarray(per_seed)
    return float(values.mean()), float(values.std(ddof=1)) if len(values) > 1 else math.nan


def _spent(cells: pd.DataFrame) -> dict[str, float]:
    """Phase-1 and second-phase steps and samples from the first cell's fit report."""
    reports = cells["fit_report"] if "fit_report" in cells else pd.Series([{}] * len(cells))
    spent = next((r["spent"] for r in reports if isinstance(r, dict) and "spent" in r), {})
    return {
        f"{phase}_{unit}": spent.get(phase, {}).get(unit, math.nan)
        for phase in ("phase1", "phase2")
        for unit in ("steps", "samples")
    }


VERSION_KEYS = ("protocol", "toolkit")
"""What must agree between the cells of one table (the profile is chosen before)."""


def versions(results: pd.DataFrame) -> pd.DataFrame:
    """Per cell: its ``protocol`` and ``toolkit`` (KKL toolkit version; None where the
    estimator records none)."""
    reports = results["fit_report"] if "fit_report" in results else pd.Series([{}] * len(results))
    return pd.DataFrame(
        {
            "protocol": results["protocol"].to_numpy(),
            "toolkit": pd.array(
                [r.get("toolkit") if isinstance(r, dict) else None for r in reports], dtype="Int64"
            ),
        },
        index=results.index,
    )


def version_groups(results: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """``results`` split by the versions that must not mix: ``{label: cells}``.

    One group (labelled ``""``) when every cell agrees; cells that record no
    toolkit version join whichever group they are in by protocol.
    """
    found = versions(results)
    toolkits = sorted(found["toolkit"].dropna().unique())
    if found["protocol"].nunique() <= 1 and len(toolkits) <= 1:
        return {"": results}
    groups = {}
    for protocol in sorted(set(found["protocol"])):
        for toolkit in toolkits or [None]:
            mask = (found["protocol"] == protocol) & (
                found["toolkit"].isna() | (found["toolkit"] == toolkit)
            )
            if mask.any():
                groups[f"protocol {protocol}, KKL toolkit {toolkit}"] = results[mask]
    return groups


def check_not_mixed(results: pd.DataFrame) -> None:
    """Raise ``ValueError`` naming what differs if the cells mix protocol or toolkit versions."""
    groups = version_groups(results)
    if len(groups) > 1:
        counts = "; ".join(f"{label}: {len(cells)} cells" for label, cells in groups.items())
        raise ValueError(
            f"the results mix versions that one table must not mix ({counts}); rerun the old "
            "cells, keep them in another results directory, or pass --by-version to tabulate "
            "each group separately"
        )


def summary_table(
    results: pd.DataFrame, with_paper: bool = False, margin: float = MARGIN
) -> pd.DataFrame:
    """One row per (estimator, system, regime): the numbers every table shows.

    Columns: estimator, system, regime, status, n_seeds, n_test (per seed),
    n_diverged (over all seeds), rmse_mean and rmse_seed_std (mean and
    standard deviation over seeds of the per-seed mean RMSE), smape_mean,
    smape_seed_std, nrmse_mean, fit_time_s, estimate_us_per_step (means over
    seeds), rmse_median (over all trajectories of all seeds), settling_median_s
    and n_unsettled (median settling time over all trajectories and how many
    never settled; NaN and 0 for cells recorded without settling times), task,
    track, protocol, map quality, the steps and samples spent
    (``phase1_steps`` ...), ``mark`` (``best``, ``tied`` or empty, see
    :mod:`kkl_bench.significance`; ``margin`` is its practical-equivalence margin) and ``rmse_trajectories`` (per seed, per
    trajectory; ``(n_seeds, n_test)`` nested lists, not written to CSV).
    """
    if "seed" not in results:
        results = results.assign(seed=0)
    columns = ["estimator", "system", "regime"]
    rows = []
    for (estimator, system, regime), cells in results.groupby(columns, sort=False):
        cells = cells.sort_values("seed")
        scored = cells[cells["status"] == "ok"]
        rmse_by_seed = [list(values) for values in scored["rmse"]]
        rmse_mean, rmse_std = _seed_mean_and_std([mean_and_std(v)[0] for v in rmse_by_seed])
        smape_mean, smape_std = _seed_mean_and_std([mean_and_std(v)[0] for v in scored["smape"]])
        pooled = [value for values in rmse_by_seed for value in values]
        settling = [value for values in scored.get("settling_time_s", []) for value in values]
        rows.append(
            {
                "estimator": estimator,
                "system": system,
                "regime": regime,
                "status": "ok" if len(scored) == len(cells) and len(scored) else "error",
                "n_seeds": len(scored),
                "n_test": len(rmse_by_seed[0]) if rmse_by_seed else 0,
                "n_diverged": sum(not math.isfinite(v) for values in rmse_by_seed for v in values),
                "rmse_mean": rmse_mean,
                "rmse_seed_std": rmse_std,
                "smape_mean": smape_mean,
                "smape_seed_std": smape_std,
                "nrmse_mean": _seed_mean_and_std([mean_and_std(v)[0] for v in scored["nrmse"]])[0],
                "fit_time_s": scored["fit_time_s"].mean(),
                "estimate_us_per_step": scored["estimate_us_per_step"].mean(),
                "rmse_median": float(np.median(pooled)) if pooled else math.nan,
                "settling_median_s": float(np.median(settling)) if settling else math.nan,
                "n_unsettled": sum(not math.isfinite(value) for value in settling),
                "task": cells["task"].iloc[0],
                "track": cells["track"].iloc[0] if "track" in cells else PAPER_TRACK,
                "protocol": cells["protocol"].iloc[0],
                **_map_quality(cells),
                **_spent(cells),
                "rmse_trajectories": rmse_by_seed,
            }
        )
    summary = pd.DataFrame(rows)
    summary["mark"] = _marks(summary, margin)
    if with_paper:
        paper = paper_results().rename(columns={"rmse": "rmse_mean", "smape_percent": "smape_mean"})
        paper["estimator"] = PAPER_PREFIX + paper.pop("method")
        paper["status"] = "ok"
        paper["n_diverged"] = 0
        paper["mark"] = ""
        summary = pd.concat([summary, paper], ignore_index=True)
    return summary


def _marks(summary: pd.DataFrame, margin: float) -> pd.Series:
    """The significance mark of every row, decided column by column."""
    marks = pd.Series("", index=summary.index, dtype=object)
    for _, column in summary.groupby(["system", "regime"], sort=False):
        scored = column[(column["status"] == "ok") & (column["n_seeds"] > 0)]
        if scored.empty or len({len(t[0]) for t in scored["rmse_trajectories"]}) != 1:
            continue  # no entries, or different test sets: nothing to compare
        decided = mark_column(
            {index: np.asarray(values) for index, values in scored["rmse_trajectories"].items()},
            margin,
        )
        for index, mark in decided.items():
            marks[index] = mark
    return marks


MAP_QUALITY = ("reconstruction_rmse_unforced", "reconstruction_rmse_forced", "pde_residual_forced")
"""Map-quality numbers a KKL estimator reports (see :func:`kkl_bench.kkl.autonomous.map_quality`)."""


def _map_quality(cells: pd.DataFrame) -> dict[str, float]:
    """The map-quality numbers in the cells' fit reports (NaN where none are reported)."""
    reports = cells["fit_report"] if "fit_report" in cells else pd.Series([{}] * len(cells))
    quality = next(
        (r["map_quality"] for r in reports if isinstance(r, dict) and "map_quality" in r), {}
    )
    return {key: quality.get(key, math.nan) for key in MAP_QUALITY}


def _format_cell(row: pd.Series, markup: dict[str, tuple[str, str]]) -> str:
    """``RMSE ± std (SMAPE)``, marked; ``diverged (k/n)`` or ``error`` where it applies."""
    if row["status"] != "ok":
        return "error"
    if row["n_diverged"]:
        return (
            f"diverged ({row['n_diverged']}/{row['n_test'] * row['n_seeds']}), "
            f"median {row['rmse_median']:.3g}"
        )
    rmse = f"{row['rmse_mean']:.3g}"
    mark = row.get("mark", "")
    if mark:
        rmse = f"{markup[mark][0]}{rmse}{markup[mark][1]}"
    spread = row.get("rmse_seed_std", math.nan)
    if isinstance(spread, float) and math.isfinite(spread):
        rmse += f" ± {spread:.2g}"
    return f"{rmse} ({row['smape_mean']:.3g})"


def _seeds(rows: pd.DataFrame) -> str:
    """How many seeds an estimator's cells have: ``3``, or ``2-3`` where they differ."""
    counts = rows["n_seeds"].dropna() if "n_seeds" in rows else pd.Series(dtype=float)
    if counts.empty:
        return ""
    low, high = int(counts.min()), int(counts.max())
    return str(low) if low == high else f"{low}-{high}"


def _format_settling(row: pd.Series) -> str:
    """Median settling time in s, with how many trajectories never settled."""
    if row["status"] != "ok" or not math.isfinite(row["settling_median_s"]):
        never = row.get("n_unsettled", 0)
        return f"never ({never}/{row['n_test'] * row['n_seeds']})" if never else "-"
    text = f"{row['settling_median_s']:.2g}"
    if row["n_unsettled"]:
        text += f" ({row['n_unsettled']}/{row['n_test'] * row['n_seeds']} never)"
    return text


def _grid(
    summary: pd.DataFrame,
    systems: Sequence[str],
    regimes: Sequence[str],
    markup: dict[str, tuple[str, str]],
    escape: Callable[[str], str] = str,
    settling: bool = False,
) -> tuple[list[str], list[list[str]]]:
    """Header and rows of one table over ``systems`` x ``regimes``; ``escape`` quotes labels.

    With ``settling``, every RMSE column is followed by a settling-time column.
    """
    estimators = list(dict.fromkeys(summary["estimator"]))
    indexed = summary.set_index(["estimator", "system", "regime"])
    header = ["Estimator", "Seeds"]
    for system in systems:
        for regime in regimes:
            header.append(
                escape(f"{SYSTEM_TITLES.get(system, system)} {REGIME_TITLES.get(regime, regime)}")
            )
            if settling:
                header.append("settle (s)")
    rows = []
    for estimator in estimators:
        own = summary[summary["estimator"] == estimator]
        row = [escape(estimator), _seeds(own)]
        for system in systems:
            for regime in regimes:
                key = (estimator, system, regime)
                found = key in indexed.index
                row.append(_format_cell(indexed.loc[key], markup) if found else "-")
                if settling:
                    row.append(_format_settling(indexed.loc[key]) if found else "-")
        rows.append(row)
    return header, rows


def _in_paper_order(names: pd.Series, known: dict[str, str]) -> list[str]:
    """Distinct ``names``: the paper's ones in its order, then any others sorted."""
    present = set(names)
    return [name for name in known if name in present] + sorted(present - set(known))


def task_order(summary: pd.DataFrame) -> list[str]:
    """The regimes (tasks) of ``summary``, one track's, in its track file's order (the
    paper's order for the paper track; sorted if the track is not installed here)."""
    present = set(summary["regime"])
    track = find_track(summary["track"].iloc[0] if "track" in summary else PAPER_TRACK)
    declared = track.task_names() if track else list(REGIME_TITLES)
    return [name for name in declared if name in present] + sorted(present - set(declared))


def _chunks(items: Sequence[str], size: int) -> list[Sequence[str]]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def render(
    summary: pd.DataFrame,
    fmt: str = "markdown",
    systems_per_table: int | None = None,
    settling: bool = False,
) -> str:
    """The leaderboard of ``summary`` (from :func:`summary_table`, one track) as text.

    ``fmt`` is ``"markdown"`` (GitHub tables), ``"latex"`` (booktabs tabulars)
    or ``"csv"`` (the summary itself, one row per estimator x cell). Tables
    hold ``systems_per_table`` systems (default: as many as keep about eight
    result columns); ``settling`` adds the settling-time columns.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; valid formats: {', '.join(FORMATS)}")
    if summary.empty:
        raise ValueError("no results to tabulate")
    if fmt == "csv":
        return summary.drop(columns="rmse_trajectories", errors="ignore").to_csv(
            index=False, float_format="%.6g"
        )
    systems = _in_paper_order(summary["system"], SYSTEM_TITLES)
    regimes = task_order(summary)
    if systems_per_table is None:
        systems_per_table = max(1, 8 // (len(regimes) * (2 if settling else 1)))
    tables = []
    for group in _chunks(systems, systems_per_table):
        if fmt == "markdown":
            header, rows = _grid(summary, group, regimes, MARKUP["markdown"], settling=settling)
            tables.append(tabulate(rows, headers=header, tablefmt="github", disable_numparse=True))
        else:
            header, rows = _grid(
                summary, group, regimes, MARKUP["latex"], _latex_escape, settling=settling
            )
            tables.append(
                _booktabs(
                    tabulate(rows, headers=header, tablefmt="latex_raw", disable_numparse=True)
                )
            )
    return "\n\n".join(tables) + "\n"


def caption(track: str, profile: str, smoke: bool, settling: bool = False) -> str:
    """What a printed table is and how to read its cells (Markdown, one paragraph)."""
    kind = " (a smoke test: its numbers say nothing about the methods)" if smoke else ""
    settle = "; `settle (s)`: median settling time" if settling else ""
    return (
        f"Track `{track}`, profile `{profile}`{kind}. A cell reads `RMSE ± std (SMAPE %)`: "
        "the steady-state RMSE, mean over test trajectories and then over the training "
        "seeds (`Seeds`), ± its standard deviation over seeds, and the mean SMAPE in %; "
        f"**bold**: lowest by a paired bootstrap with a {100 * MARGIN:g} % margin, *italics*: "
        f"tied with the lowest{settle}.\n"
    )


def _latex_escape(text: str) -> str:
    for character in "&%$#_{}":
        text = text.replace(character, "\\" + character)
    return text


def _booktabs(latex: str) -> str:
    """Turn tabulate's ``latex_raw`` rules (three ``\\hline``) into booktabs rules."""
    rules = iter([r"\toprule", r"\midrule", r"\bottomrule"])
    return "\n".join(
        next(rules) if line.strip() == r"\hline" else line for line in latex.splitlines()
    )


COST_COLUMNS = {
    "fit_time_s": "Fit time (s)",
    "estimate_us_per_step": "Estimation (µs / trajectory-step)",
    "phase1_steps": "Phase 1 steps",
    "phase1_samples": "Phase 1 samples",
    "phase2_steps": "2nd phase steps",
    "phase2_samples": "2nd phase samples",
    "nrmse_mean": "NRMSE (mean over regimes)",
    "reconstruction_rmse_unforced": "|x - T*(T(x))| unforced",
    "reconstruction_rmse_forced": "|x - T*(T(x))| forced",
    "pde_residual_forced": "PDE residual (rel.) forced",
}
"""The cost table's columns: per (estimator, system), means over regimes and seeds."""


def cost_frame(summary: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, system): costs, training budget spent, NRMSE and map quality."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    grouped = ours.groupby(["estimator", "system"]).agg(
        **{
            key: (key, "first" if key in MAP_QUALITY or "phase" in key else "mean")
            for key in COST_COLUMNS
        }
    )
    order = {system: i for i, system in enumerate(_in_paper_order(ours["system"], SYSTEM_TITLES))}
    return grouped.reset_index().sort_values(
        ["estimator", "system"], key=lambda c: c.map(order) if c.name == "system" else c
    )


def cost_table(summary: pd.DataFrame) -> str:
    """Markdown table per (estimator, system): fit time, estimation cost, the optimizer
    steps and samples of Phase 1 (shared by the KKL rows of a system) and of the
    estimator's own second phase, NRMSE and, for KKL estimators, the quality of their maps."""
    rows = cost_frame(summary)
    rows = rows.astype(object).where(rows.notna(), None)
    return tabulate(
        rows,
        headers=["Estimator", "System", *COST_COLUMNS.values()],
        tablefmt="github",
        floatfmt=".3g",
        intfmt=",",
        showindex=False,
        missingval="",
    )


def measured_cost_table(costs: pd.DataFrame) -> str:
    """Markdown table of a ``kkl-bench cost`` measurement (:mod:`kkl_bench.cost`): per
    estimator, the µs per trajectory-step on each system (mean over its tasks), the
    largest over all cells, and how many times cheaper than the EKF it is on average:
    per system, the mean of the EKF's costs timed in each row's own run over the mean of
    the row's, averaged over the systems."""
    means = costs.groupby(["estimator", "system"])[
        ["us_per_trajectory_step", "reference_us_per_trajectory_step"]
    ].mean()
    per_system = means["us_per_trajectory_step"].unstack("system")
    systems = _in_paper_order(per_system.columns, SYSTEM_TITLES)
    table = per_system[systems].rename(columns=lambda name: SYSTEM_TITLES.get(name, name))
    table["largest cell"] = costs.groupby("estimator")["us_per_trajectory_step"].max()
    ratios = (means["reference_us_per_trajectory_step"] / means["us_per_trajectory_step"]).unstack(
        "system"
    )
    table["EKF / this (mean over systems)"] = ratios[systems].mean(axis=1)
    return tabulate(
        table.reset_index(),
        headers=["Estimator (µs / trajectory-step)", *table.columns],
        tablefmt="github",
        floatfmt=".3g",
        showindex=False,
    )


def paper_comparison(summary: pd.DataFrame) -> str:
    """Markdown table: our RMSE over the paper's for each of the paper's methods and cells."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)].set_index(
        ["estimator", "system", "regime"]
    )
    paper = paper_results()
    systems = _in_paper_order(paper["system"], SYSTEM_TITLES)
    regimes = _in_paper_order(paper["regime"], REGIME_TITLES)
    header = ["Method (ours / paper)"] + [
        f"{SYSTEM_TITLES[s]} {REGIME_TITLES[r]}" for s in systems for r in regimes
    ]
    rows = []
    for method, theirs in paper.groupby("method", sort=False):
        theirs = theirs.set_index(["system", "regime"])["rmse"]
        row = [method]
        for system in systems:
            for regime in regimes:
                key = (method, system, regime)
                if key not in ours.index:
                    row.append("-")
                    continue
                ratio = ours.loc[key, "rmse_mean"] / theirs[system, regime]
                row.append(f"{ratio:.2g}x" if math.isfinite(ratio) else "diverged")
        rows.append(row)
    return tabulate(rows, headers=header, tablefmt="github", disable_numparse=True)


COMPARISON_COLUMNS = (
    "cell",
    "system",
    "regime",
    "rmse_a",
    "rmse_b",
    "ratio",
    "low",
    "high",
    "verdict",
)
"""Columns of :func:`comparison_frame`."""


def comparison_frame(summary: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per cell both estimators scored: ``a``'s RMSE over ``b``'s, its 90 % bootstrap
    interval (``low``, ``high``) and the verdict of :func:`kkl_bench.significance.compare`
    (``"a lower"``, ``"b lower"``, ``"not distinguishable"`` or ``"diverged"``), in paper
    order; columns :data:`COMPARISON_COLUMNS`."""
    indexed = summary.set_index(["estimator", "system", "regime"])
    for name in (a, b):
        if name not in set(summary["estimator"]):
            raise ValueError(
                f"no results for {name!r}; estimators in the results: "
                f"{', '.join(sorted(set(summary['estimator'])))}"
            )
    rows = []
    for system in _in_paper_order(summary["system"], SYSTEM_TITLES):
        for regime in _in_paper_order(summary["regime"], REGIME_TITLES):
            if (a, system, regime) not in indexed.index or (b, system, regime) not in indexed.index:
                continue
            first, second = indexed.loc[(a, system, regime)], indexed.loc[(b, system, regime)]
            if first["status"] != "ok" or second["status"] != "ok":
                continue
            result = compare(
                np.asarray(first["rmse_trajectories"]), np.asarray(second["rmse_trajectories"])
            )
            rows.append(
                {
                    "cell": f"{SYSTEM_TITLES.get(system, system)} {REGIME_TITLES.get(regime, regime)}",
                    "system": system,
                    "regime": regime,
                    "rmse_a": first["rmse_mean"],
                    "rmse_b": second["rmse_mean"],
                    **result,
                }
            )
    return pd.DataFrame(rows, columns=list(COMPARISON_COLUMNS))


def comparison_cells(frame: pd.DataFrame, last: Sequence[str]) -> list[list[str]]:
    """Each row of a :func:`comparison_frame` as printed: cell, both RMSEs, ratio and
    ``[low, high]`` (3 significant digits), then the row's item of ``last``."""
    return [
        [
            row.cell,
            f"{row.rmse_a:.3g}",
            f"{row.rmse_b:.3g}",
            f"{row.ratio:.3g}",
            f"[{row.low:.3g}, {row.high:.3g}]",
            extra,
        ]
        for row, extra in zip(frame.itertuples(), last, strict=True)
    ]


def comparison_table(summary: pd.DataFrame, a: str, b: str) -> str:
    """Markdown table of :func:`comparison_frame`, verdicts naming the estimators."""
    frame = comparison_frame(summary, a, b)
    names = {"a lower": f"{a} lower", "b lower": f"{b} lower"}
    verdicts = [names.get(verdict, verdict) for verdict in frame["verdict"]]
    return tabulate(
        comparison_cells(frame, verdicts),
        headers=["Cell", f"RMSE {a}", f"RMSE {b}", "ratio", "90 % interval", "verdict (5 %)"],
        tablefmt="github",
        disable_numparse=True,
    )


LIMIT = "particle_filter"
"""The row the other estimators are measured against in :func:`limit_frame`."""
MODEL_BASED = ("ekf", "ukf", LIMIT)
"""Estimators given the exact model and nothing learned; every other row is a learned one."""
LIMIT_COLUMNS = {
    "system": "System",
    "regime": "Regime",
    "limit_rmse": "Particle filter RMSE",
    "ekf": "EKF / limit",
    "ukf": "UKF / limit",
    "best_learned": "Best learned",
    "best_learned_ratio": "Best learned / limit",
}


def limit_frame(summary: pd.DataFrame) -> pd.DataFrame:
    """Per cell: the particle filter's RMSE (the posterior mean under the exact model, the
    least any estimator can expect) and the EKF's, the UKF's and the best learned row's
    RMSE over it (:data:`LIMIT_COLUMNS`). Empty without particle-filter results."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    ok = ours[ours["status"] == "ok"].set_index(["estimator", "system", "regime"])["rmse_mean"]
    learned = [
        e for e in dict.fromkeys(ours["estimator"]) if variants.base_name(e) not in MODEL_BASED
    ]
    rows = []
    for system in _in_paper_order(ours["system"], SYSTEM_TITLES):
        for regime in _in_paper_order(ours["regime"], REGIME_TITLES):
            limit = ok.get((LIMIT, system, regime), math.nan)
            if not math.isfinite(limit):
                continue
            candidates = {e: ok[(e, system, regime)] for e in learned if (e, system, regime) in ok}
            best = min(candidates, key=candidates.get) if candidates else ""
            rows.append(
                {
                    "system": system,
                    "regime": regime,
                    "limit_rmse": limit,
                    "ekf": ok.get(("ekf", system, regime), math.nan) / limit,
                    "ukf": ok.get(("ukf", system, regime), math.nan) / limit,
                    "best_learned": best,
                    "best_learned_ratio": candidates[best] / limit if best else math.nan,
                }
            )
    return pd.DataFrame(rows, columns=list(LIMIT_COLUMNS))


def limit_table(summary: pd.DataFrame) -> str:
    """:func:`limit_frame` as Markdown (empty string without particle-filter results)."""
    frame = limit_frame(summary)
    if frame.empty:
        return ""
    frame = frame.assign(
        system=frame["system"].map(lambda s: SYSTEM_TITLES.get(s, s)),
        regime=frame["regime"].map(lambda r: REGIME_TITLES.get(r, r)),
    )
    return tabulate(
        frame,
        headers=list(LIMIT_COLUMNS.values()),
        tablefmt="github",
        floatfmt=".3g",
        showindex=False,
    )


def _finite_mean(rmse_trajectories: list[list[float]]) -> float:
    """Mean RMSE over the trajectories (of all seeds) that did not diverge."""
    values = [v for seed in rmse_trajectories for v in seed if math.isfinite(v)]
    return float(np.mean(values)) if values else math.nan


def _reference(track: str, regime: str) -> str:
    """The paper task ``track``'s task ``regime`` is compared with (its own name if the
    track is not installed here)."""
    declared = find_track(track)
    if declared is None or regime not in declared.task_names():
        return regime
    return declared.task(regime).reference


def condition(track: str, regime: str) -> str:
    """What task ``regime`` of ``track`` changes beside its reference regime: its name
    without the reference (``params10-square`` -> ``params10``, ``square-sigma0.1`` ->
    ``sigma0.1``), or the whole name if it does not contain it (``chirp``)."""
    reference = _reference(track, regime)
    if regime.startswith(f"{reference}-"):
        return regime[len(reference) + 1 :]
    if regime.endswith(f"-{reference}"):
        return regime[: -len(reference) - 1]
    return regime


def track_summary(results: pd.DataFrame, by_condition: bool = False) -> pd.DataFrame:
    """Per estimator and track: RMSE relative to the estimator's own paper-track RMSE.

    For each of the track's cells, the mean RMSE over its non-diverged
    trajectories (all seeds) divided by the same estimator's mean paper-track
    RMSE on the same system under the task's reference regime (declared in
    the track file); ``ratio`` is the geometric mean of these over the
    track's cells. ``n_diverged`` and ``n_trajectories`` count the track's
    diverged and scored trajectories. A track with no cell to compare (one of
    other systems, such as ``more-systems``) is left out. Columns: estimator,
    track, ratio, n_cells, n_diverged, n_trajectories; ``by_condition``: one row
    per estimator, track and :func:`condition` (column ``condition``, after
    ``track``), e.g. the mismatch track's ``params10``, ``params25`` and ``sensor``.
    """
    if "track" not in results:
        results = results.assign(track=PAPER_TRACK)
    per_track = {
        track: summary_table(cells) for track, cells in results.groupby("track", sort=False)
    }
    if PAPER_TRACK not in per_track:
        raise ValueError("the results hold no paper-track cells to compare the tracks with")
    paper = per_track[PAPER_TRACK].set_index(["estimator", "system", "regime"])
    cells = []
    for track, summary in per_track.items():
        if track == PAPER_TRACK:
            continue
        for cell in summary[summary["status"] == "ok"].itertuples():
            # a +logged row is compared with its estimator's own paper-track fit
            nominal = variants.split_logged(cell.estimator)[0]
            key = (nominal, cell.system, _reference(track, cell.regime))
            ratio = math.nan
            if key in paper.index and paper.loc[key, "status"] == "ok":
                ratio = _finite_mean(cell.rmse_trajectories) / _finite_mean(
                    paper.loc[key, "rmse_trajectories"]
                )
            cells.append(
                {
                    "estimator": cell.estimator,
                    "track": track,
                    "condition": condition(track, cell.regime),
                    "ratio": ratio if math.isfinite(ratio) and ratio > 0 else math.nan,
                    "n_diverged": cell.n_diverged,
                    "n_trajectories": cell.n_test * cell.n_seeds,
                }
            )
    keys = ["estimator", "track", *(["condition"] if by_condition else [])]
    columns = [*keys, "ratio", "n_cells", "n_diverged", "n_trajectories"]
    if not cells:
        return pd.DataFrame(columns=columns)
    frame = (
        pd.DataFrame(cells)
        .groupby(keys, sort=False)
        .agg(
            ratio=("ratio", lambda r: float(np.exp(np.log(r.dropna()).mean()))),
            n_cells=("ratio", "count"),
            n_diverged=("n_diverged", "sum"),
            n_trajectories=("n_trajectories", "sum"),
        )
        .reset_index()[columns]
    )
    comparable = frame.groupby("track")["n_cells"].transform("sum") > 0
    return frame[comparable].reset_index(drop=True)


def render_track_summary(frame: pd.DataFrame, column: str = "track") -> str:
    """Markdown: estimators as rows, the values of ``column`` (``track``, or ``condition``
    for one track's :func:`track_summary` by condition) as columns, ``ratio`` (and
    diverged counts)."""
    headers = list(dict.fromkeys(frame[column]))
    indexed = frame.set_index(["estimator", column])
    rows = []
    for estimator in dict.fromkeys(frame["estimator"]):
        row = [estimator]
        for header in headers:
            if (estimator, header) not in indexed.index:
                row.append("-")
                continue
            cell = indexed.loc[(estimator, header)]
            text = f"{cell['ratio']:.3g}x" if math.isfinite(cell["ratio"]) else "-"
            if cell["n_diverged"]:
                text += f" ({int(cell['n_diverged'])}/{int(cell['n_trajectories'])} diverged)"
            row.append(text)
        rows.append(row)
    return tabulate(rows, headers=["Estimator", *headers], tablefmt="github", disable_numparse=True)
