"""Figures drawn from stored results alone (matplotlib, the optional ``plot`` extra).

* :func:`trajectory_figure`: per (system, regime), each state's truth and
  every estimator's estimate over time on test trajectory 0 (the paper's
  appendix figure), and below them the estimation-error norm on a log scale;
* :func:`relative_rmse_heatmap`: each estimator's RMSE over the UKF's, per cell;
* :func:`cost_accuracy_figure`: estimation cost against RMSE, one panel per system.

Every figure is saved as PNG (for Markdown) and SVG (for the page) by
:func:`save`, with fixed metadata so that the same results give the same bytes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from kkl_bench import families
from kkl_bench.analysis.summary import PAPER_PREFIX, REGIME_TITLES, SYSTEM_TITLES, task_order
from kkl_bench.run.results import KeptEstimate

REFERENCE = "ukf"
"""The estimator the heat map divides by."""


def pyplot():
    """matplotlib's pyplot on the non-interactive Agg backend, its SVG ids salted alike in
    every run (:func:`save`)."""
    try:
        import matplotlib
    except ImportError:
        raise ImportError(
            "figures need matplotlib: pip install 'kkl-bench[plot]' (or pip install matplotlib)"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"svg.hashsalt": "kkl-bench", "font.size": 9, "axes.titlesize": 10})
    return plt


MARKERS = ("o", "s", "^", "D", "v")
"""Markers cycled with the colours, so that no two of 20 lines look alike."""


def _colors(names: Sequence[str]) -> dict[str, tuple]:
    """One stable colour per estimator (tab10, then tab20)."""
    plt = pyplot()
    palette = list(plt.get_cmap("tab10").colors) + list(plt.get_cmap("tab20").colors[1::2])
    return {name: palette[i % len(palette)] for i, name in enumerate(sorted(names))}


def trajectory_figure(title: str, kept: Mapping[str, KeptEstimate]):
    """States and error norm over time on one test trajectory for every estimator in ``kept``.

    ``kept`` maps estimator names to their kept estimate of the same test
    trajectory (same truth).
    """
    plt = pyplot()
    names = sorted(kept)
    truth = kept[names[0]]
    n_x = truth.x.shape[1]
    colors = _colors(names)
    figure, axes = plt.subplots(
        n_x + 1, 1, figsize=(9, 1.9 * (n_x + 1)), sharex=True, constrained_layout=True
    )
    dense = {
        "rasterized": True
    }  # 1000-sample lines: pixels inside the SVG, axes and text stay vector
    for state, axis in enumerate(axes[:n_x]):
        axis.plot(truth.t, truth.x[:, state], color="black", linewidth=2.2, label="truth", **dense)
        for name in names:
            axis.plot(
                truth.t,
                kept[name].x_hat[:, state],
                color=colors[name],
                linewidth=0.9,
                label=name,
                **dense,
            )
        axis.set_ylabel(f"$x_{state + 1}$")
        low, high = np.min(truth.x[:, state]), np.max(truth.x[:, state])
        margin = 0.5 * (high - low) + 1e-6
        axis.set_ylim(low - margin, high + margin)  # an estimate far off does not hide the rest
    error_axis = axes[n_x]
    for name in names:
        error = np.linalg.norm(kept[name].x_hat - kept[name].x, axis=1)
        error_axis.semilogy(
            truth.t, np.where(error > 0, error, np.nan), color=colors[name], linewidth=0.9, **dense
        )
    error_axis.set_ylabel(r"$\|\hat{x} - x\|$")
    error_axis.set_xlabel("time (s)")
    for axis in axes:
        axis.grid(alpha=0.3)
    axes[0].set_title(f"{title}: test trajectory 0")
    figure.legend(
        *axes[0].get_legend_handles_labels(), loc="outside right upper", fontsize=8, frameon=False
    )
    return figure


RATIO_CAP = 100.0
"""Largest RMSE ratio the heat maps' colour scale distinguishes."""


def relative_ratios(
    summary: pd.DataFrame,
) -> tuple[list[str], list[tuple[str, str]], np.ndarray]:
    """The estimators, the (system, regime) cells and ``(estimators, cells)`` ratios of each
    estimator's mean RMSE to the UKF's (NaN where either is missing or the UKF diverged; the
    UKF's own entry inf where it diverged, so that the figure says why its column is empty).
    A row whose every cell is ``unsupported`` (the tables give its reason) is left out."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    if "status" in ours:
        ours = ours[ours["estimator"].isin(ours.loc[ours["status"] != "unsupported", "estimator"])]
    regimes = task_order(ours)
    systems = [s for s in SYSTEM_TITLES if s in set(ours["system"])]
    systems += sorted(set(ours["system"]) - set(systems))
    cells = [
        (s, r) for s in systems for r in regimes if ((ours.system == s) & (ours.regime == r)).any()
    ]
    table = ours.set_index(["estimator", "system", "regime"])["rmse_mean"]
    names = sorted(set(ours["estimator"]))
    ratios = np.full((len(names), len(cells)), np.nan)
    for i, name in enumerate(names):
        for j, (system, regime) in enumerate(cells):
            if (name, system, regime) in table.index and (REFERENCE, system, regime) in table.index:
                reference = table[REFERENCE, system, regime]
                if name == REFERENCE:
                    ratios[i, j] = 1.0 if np.isfinite(reference) else math.inf
                else:
                    ratios[i, j] = over_reference(table[name, system, regime], reference)
    return names, cells, ratios


def over_reference(rmse: float, reference: float) -> float:
    """``rmse / reference``, or NaN where the reference (the UKF) diverged or is missing: no
    row is infinitely better than a UKF that lost a trajectory."""
    return rmse / reference if np.isfinite(reference) and reference > 0 else math.nan


def relative_rmse_heatmap(summary: pd.DataFrame, title: str = ""):
    """Heat map of each estimator's mean RMSE over the UKF's per cell (log colour scale).

    ``summary`` holds one track's cells; ``title`` prefixes the figure's title.
    """
    plt = pyplot()
    from matplotlib.colors import LogNorm

    names, cells, ratios = relative_ratios(summary)
    finite = ratios[np.isfinite(ratios)]
    figure, axis = plt.subplots(
        figsize=(2.5 + 0.62 * len(cells), 2.2 + 0.42 * len(names)), constrained_layout=True
    )
    # Colours saturate at RATIO_CAP (the printed numbers do not): one blown-up cell
    # (1e31) would otherwise wash every other cell out to the same colour.
    norm = (
        LogNorm(
            vmin=min(max(finite.min(), 0.5), RATIO_CAP / 2),
            vmax=min(max(finite.max(), 2.0), RATIO_CAP),
        )
        if finite.size
        else None
    )
    image = axis.imshow(
        np.where(np.isfinite(ratios), ratios, np.nan), cmap="RdYlGn_r", norm=norm, aspect="auto"
    )
    for i in range(len(names)):
        for j in range(len(cells)):
            value = ratios[i, j]
            text = "-" if np.isnan(value) else ("div." if math.isinf(value) else f"{value:.2g}")
            axis.text(j, i, text, ha="center", va="center", fontsize=7)
    axis.set_xticks(
        range(len(cells)),
        [f"{SYSTEM_TITLES.get(s, s)} {REGIME_TITLES.get(r, r)}" for s, r in cells],
        rotation=60,
        ha="right",
    )
    shown = families.shown_names(summary)
    axis.set_yticks(range(len(names)), [shown.get(name, name) for name in names])
    axis.set_title(
        f"{title}RMSE relative to the {REFERENCE.upper()} (mean over seeds; 1 = as good)"
    )
    figure.colorbar(
        image, ax=axis, label=f"RMSE / RMSE of {REFERENCE} (colour saturates at {RATIO_CAP:g})"
    )
    return figure


OFF_SCALE = 100.0
"""A panel's RMSE axis reaches at most this many times its median entry; entries beyond
(a diverging row) are drawn at the edge with their value written."""


def cost_accuracy_figure(summary: pd.DataFrame):
    """Estimation cost (µs per trajectory-step) against mean RMSE over regimes, per system.

    An entry whose RMSE is more than :data:`OFF_SCALE` times the panel's median entry is
    drawn at the panel's top edge (a triangle) with its value written, so that one
    diverging row does not flatten the others.
    """
    plt = pyplot()
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    systems = [s for s in SYSTEM_TITLES if s in set(ours["system"])]
    names = sorted(set(ours["estimator"]))
    colors = _colors(names)
    markers = "osD^vP*Xh<>"
    figure, axes = plt.subplots(
        1,
        len(systems),
        figsize=(3.2 * len(systems) + 2.4, 3.4),
        constrained_layout=True,
        squeeze=False,
    )
    for axis, system in zip(axes[0], systems, strict=True):
        rows = (
            ours[ours["system"] == system]
            .groupby("estimator")[["estimate_us_per_step", "rmse_mean"]]
            .mean()
        )
        rows = rows[np.isfinite(rows).all(axis=1)]
        edge = OFF_SCALE * float(rows["rmse_mean"].median()) if len(rows) else math.inf
        for i, name in enumerate(names):
            if name not in rows.index:
                continue
            cost, rmse = rows.loc[name]
            style = {"marker": markers[i % len(markers)], "color": colors[name], "label": name}
            if rmse > edge:
                axis.loglog(cost, edge, linestyle="none", **(style | {"marker": "^"}))
                axis.annotate(
                    f"{name}: {rmse:.2g}",
                    (cost, edge),
                    xytext=(0, -10),
                    textcoords="offset points",
                    ha="center",
                    fontsize=6,
                    color=colors[name],
                )
            else:
                axis.loglog(cost, rmse, linestyle="none", **style)
        if len(rows) and rows["rmse_mean"].max() > edge:
            axis.set_ylim(top=edge * 1.5)
        axis.set_title(SYSTEM_TITLES[system])
        axis.set_xlabel("estimation cost (µs / trajectory-step)")
        axis.grid(alpha=0.3, which="both")
    axes[0][0].set_ylabel("RMSE (mean over regimes and seeds)")
    handles = {
        label: handle
        for axis in axes[0]
        for handle, label in zip(*axis.get_legend_handles_labels(), strict=True)
    }
    figure.legend(
        handles.values(), handles.keys(), loc="outside right upper", fontsize=8, frameon=False
    )
    return figure


def curves_figure(curves: pd.DataFrame):
    """Validation curves against the share of the budget spent, one panel per estimator,
    one line per size (colour) and training (line style); ``curves``: the scaling
    study's :func:`kkl_bench.analysis.scaling.curve_frame`."""
    plt = pyplot()
    names = sorted(set(curves["estimator"]))
    sizes = sorted(set(curves["n"]))
    shades = plt.get_cmap("viridis")
    colors = {n: shades(i / max(1, len(sizes) - 1)) for i, n in enumerate(sizes)}
    styles = ("-", "--", ":", "-.")
    columns = min(3, len(names))
    rows = math.ceil(len(names) / columns)
    figure, axes = plt.subplots(
        rows, columns, figsize=(4.6 * columns, 3.4 * rows), squeeze=False, layout="constrained"
    )
    for axis, name in zip(axes.flat, names, strict=False):
        of = curves[curves["estimator"] == name]
        trainings = list(dict.fromkeys(of["training"]))
        for (n, training), curve in of.groupby(["n", "training"], sort=True):
            axis.semilogy(
                curve["step"] / curve["step"].max(),
                curve["error"],
                color=colors[n],
                linestyle=styles[trainings.index(training) % len(styles)],
                marker=".",
                label=f"n = {n}" + (f", {training}" if len(trainings) > 1 else ""),
            )
        axis.set_title(name, fontsize=9)
        axis.set_xlabel("share of the training's steps")
        axis.grid(alpha=0.3, which="both")
        axis.legend(fontsize=6)
    for axis in axes.flat[len(names) :]:
        axis.set_visible(False)
    figure.suptitle("Lorenz-96: validation error along each training (protocol 6.5)")
    return figure


def save(figure, path_without_suffix: Path) -> list[Path]:
    """Write ``figure`` as PNG and SVG, without dates or versions, so one machine writes
    the same bytes each time (another machine's SVG may differ in the sixth decimal of a
    coordinate); returns both paths."""
    plt = pyplot()
    path_without_suffix.parent.mkdir(parents=True, exist_ok=True)
    paths = []
    for suffix, metadata in (
        (".png", {"Software": None}),
        (".svg", {"Date": None, "Creator": None}),
    ):
        path = path_without_suffix.with_suffix(suffix)
        figure.savefig(path, dpi=110, metadata=metadata)
        paths.append(path)
    plt.close(figure)
    return paths


def scaling_figure(frame: pd.DataFrame, panels: Mapping[str, str]):
    """Log-log panels of each column of ``panels`` (column -> title: the RMSE and the costs)
    against the state dimension, one legend for all (``frame``: the scaling study,
    :func:`kkl_bench.analysis.scaling.scaling_frame`; the fitted exponents are in its tables)."""
    plt = pyplot()
    names = sorted(set(frame["estimator"]))
    colors = _colors(names)
    markers = {name: MARKERS[i % len(MARKERS)] for i, name in enumerate(names)}
    figure, axes = plt.subplots(
        1, len(panels), figsize=(4.4 * len(panels), 6.2), layout="constrained"
    )
    handles = {}
    for axis, (column, label) in zip(axes, panels.items(), strict=True):
        for name in names:
            rows_of = frame[(frame["estimator"] == name) & np.isfinite(frame[column])]
            if not rows_of.empty:
                (handles[name],) = axis.loglog(
                    rows_of["n"], rows_of[column], marker=markers[name], color=colors[name]
                )
        axis.set_xlabel("state dimension n")
        axis.set_title(label)
        axis.set_xticks(sorted(set(frame["n"])), [str(n) for n in sorted(set(frame["n"]))])
        axis.xaxis.set_minor_formatter(plt.NullFormatter())  # only the measured sizes
        axis.grid(alpha=0.3, which="both")
    ordered = [name for name in names if name in handles]
    figure.legend([handles[name] for name in ordered], ordered, loc="outside lower center", ncol=5)
    figure.suptitle("Lorenz-96: error and cost against the state dimension")
    return figure
