"""``kkl-bench publish``: the whole leaderboard folder from stored results alone.

Writes, for one profile:

* ``README.md`` and ``index.html``: the same sections (:mod:`kkl_bench.report.board`,
  :mod:`~kkl_bench.report.tracks`, :mod:`~kkl_bench.report.provenance`) rendered as
  Markdown and as a self-contained page with a panel per track;
* ``<profile>.tex`` (booktabs) and ``<profile>.csv`` (tidy numbers), and
  ``<profile>-<track>.tex`` / ``.csv`` for every other track;
* ``figures/``: PNG (for the Markdown) and SVG (for the page);
* ``publication.json``: the profile, the results folder and the files written, by
  which later publications know what they may replace.

Nothing is timed or dated here, so the same results give byte-identical files.
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm import tqdm

from kkl_bench import figures
from kkl_bench.cost import COST_FILE, read_costs, with_measured_costs
from kkl_bench.leaderboard import render
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.report import html, markdown
from kkl_bench.report.board import Board, TrackTables, introduction, paper_sections, reading_guide
from kkl_bench.report.model import Section
from kkl_bench.report.provenance import failed_seeds, provenance_sections, runs_frame
from kkl_bench.report.scaling import study_panel
from kkl_bench.report.tracks import settles, track_sections
from kkl_bench.results import kept_estimates
from kkl_bench.significance import MARGIN
from kkl_bench.summary import PAPER_PREFIX, REGIME_TITLES, SYSTEM_TITLES, summary_table
from kkl_bench.task import ProfileError, get_profile
from kkl_bench.tracks import find_track
from kkl_bench.verification import VERIFICATION_FILE, read_verifications

MANIFEST = "publication.json"
"""The file by which ``publish`` owns its folder: profile, results folder and files written."""


class PublishRefused(ValueError):
    """The output folder holds a board this publication must not overwrite."""


def sections(board: Board) -> list[Section]:
    """Every section of the board, in reading order."""
    return [
        introduction(board),
        reading_guide(board),
        *paper_sections(board),
        *track_sections(board),
        *([board.scaling_panel] if board.scaling_panel else []),
        *provenance_sections(board),
    ]


def title(board: Board) -> str:
    protocol = ", ".join(sorted(set(board.results["protocol"])))
    return f"Leaderboard: profile `{board.profile}`, protocol {protocol}"


def page_filters(summary: pd.DataFrame) -> dict[str, dict[str, str]]:
    """The page's system and regime filters: the paper track's, with their titles."""
    ours = summary[~summary["estimator"].str.startswith(PAPER_PREFIX)]
    return {
        "system": {k: v for k, v in SYSTEM_TITLES.items() if k in set(ours["system"])},
        "regime": {k: v for k, v in REGIME_TITLES.items() if k in set(ours["regime"])},
    }


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
        verifications=read_verifications(out / VERIFICATION_FILE),
        scaling_panel=study_panel(out, profile),
        every_cell=results,
    )
    parts = sections(board)
    written = {
        "README.md": markdown.document(title(board), parts),
        f"{profile}.tex": render(summary, "latex"),
        f"{profile}.csv": render(
            summary[~summary["estimator"].str.startswith(PAPER_PREFIX)], "csv"
        ),
        "index.html": html.document(title(board), parts, page_filters(summary)),
    }
    for name, track_summary_frame in tables.summaries.items():
        written[f"{profile}-{name}.tex"] = render(
            track_summary_frame, "latex", settling=settles(name)
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


def draw_figures(
    summary: pd.DataFrame,
    results_dir: Path,
    profile: str,
    out: Path,
    tracks: dict[str, pd.DataFrame] | None = None,
) -> list[str]:
    """Draw every figure into ``out/figures`` (PNG and SVG), with a progress bar; returns
    their names.

    ``summary`` is the paper track's; each of ``tracks`` (name -> summary) gets
    its own heat map.
    """
    kept = kept_estimates(results_dir, profile)
    drawings = [("relative-rmse", lambda: figures.relative_rmse_heatmap(summary))]
    for name, of_track in (tracks or {}).items():
        drawings.append(
            (
                f"relative-rmse-{name}",
                functools.partial(figures.relative_rmse_heatmap, of_track, f"Track {name}: "),
            )
        )
        if settles(name):  # where the first test trajectory starts matters: draw it
            drawings += _track_trajectories(name, results_dir, profile)
    drawings.append(("cost-accuracy", lambda: figures.cost_accuracy_figure(summary)))
    for system in SYSTEM_TITLES:
        for regime in REGIME_TITLES:
            cell = {e: k for (e, s, r), k in kept.items() if (s, r) == (system, regime)}
            if cell:
                title = f"{SYSTEM_TITLES[system]}, {regime} input"
                drawings.append(
                    (
                        f"trajectory-{system}-{regime}",
                        functools.partial(figures.trajectory_figure, title, cell),
                    )
                )
    directory = out / "figures"
    for name, draw in tqdm(drawings, desc="drawing figures", unit="figure", disable=None):
        figures.save(draw(), directory / name)
    return [name for name, _ in drawings]


def _track_trajectories(track: str, results_dir: Path, profile: str) -> list[tuple[str, Any]]:
    """``(name, draw)`` of test trajectory 0 of ``track``'s first task on every system."""
    kept = kept_estimates(results_dir, profile, track)
    declared = find_track(track)
    first = declared.task_names()[0] if declared else min(r for _, _, r in kept)
    drawings = []
    for system in SYSTEM_TITLES:
        cell = {e: k for (e, s, r), k in kept.items() if (s, r) == (system, first)}
        if cell:
            title = f"Track {track}: {SYSTEM_TITLES[system]}, {first} input"
            drawings.append(
                (
                    f"track-{track}-{system}-{first}",
                    functools.partial(figures.trajectory_figure, title, cell),
                )
            )
    return drawings
