"""``kkl-bench publish``: the whole leaderboard folder from stored results alone.

Writes, for one profile:

* ``README.md`` and ``index.html``: the same sections (:mod:`kkl_bench.report.board`,
  :mod:`~kkl_bench.report.tracks`, :mod:`~kkl_bench.report.provenance`) rendered as
  Markdown and as a self-contained page with a panel per track;
* ``<profile>.tex`` (booktabs) and ``<profile>.csv`` (tidy numbers), and
  ``<profile>-<track>.tex`` / ``.csv`` for every other track;
* ``figures/``: PNG (for the Markdown) and SVG (for the page);
* ``publication.json``: the profile, the results folder and the files written, by
  which later publications know what they may replace, and a digest of each figure's
  inputs and files.

Nothing is timed or dated here, so the same results give byte-identical files; a figure
whose inputs (its data, the drawing code, matplotlib's version) and files are those
the previous publication recorded is kept, not drawn again (adding one row to a board
redraws the few figures that show it).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import pickle
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm import tqdm

from kkl_bench.analysis import figures
from kkl_bench.analysis.cost import COST_FILE, read_costs, with_measured_costs
from kkl_bench.analysis.document import Section
from kkl_bench.analysis.significance import MARGIN
from kkl_bench.analysis.summary import (
    PAPER_PREFIX,
    REGIME_TITLES,
    SYSTEM_TITLES,
    summary_table,
    with_paper_rows,
)
from kkl_bench.protocol.streams import PAPER_TRACK
from kkl_bench.report import html, markdown
from kkl_bench.report.board import Board, TrackTables, introduction, paper_sections, reading_guide
from kkl_bench.report.provenance import failed_seeds, provenance_sections, runs_frame
from kkl_bench.report.scaling import study_panel
from kkl_bench.report.text import render
from kkl_bench.report.tracks import settles, track_sections
from kkl_bench.run.ledger import ledger_summary, read_ledger
from kkl_bench.run.results import kept_estimates
from kkl_bench.run.verification import VERIFICATION_FILE, read_verifications
from kkl_bench.suite.task import ProfileError, get_profile
from kkl_bench.suite.tracks import find_track
from kkl_bench.support.cache import imported_code_digest

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
    :func:`~kkl_bench.run.results.load_results` of ``results_dir``) into ``out``.

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
    previous, previous_figures = owned_files(out, profile, link, force)
    paper_summary = summary_table(paper, margin=margin)
    summary = with_paper_rows(paper_summary)
    costs = read_costs(out / COST_FILE)
    if costs is not None:
        costs = costs[costs["track"] == PAPER_TRACK]
        summary = with_measured_costs(summary, costs)
    tables = TrackTables.of(results, margin, paper_summary)
    out.mkdir(parents=True, exist_ok=True)
    figure_digests = draw_figures(
        summary, results_dir, profile, out, tables.summaries, previous_figures
    )
    figure_names = list(figure_digests)
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
        regeneration=ledger_summary(read_ledger(results_dir)),
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
    manifest = {"profile": profile, "results": link, "files": files, "figures": figure_digests}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return [out / name for name in files]


def _is_smoke(profile: str) -> bool:
    """Whether ``profile`` is a smoke test (False for a profile not installed here)."""
    try:
        return get_profile(profile).smoke
    except ProfileError:
        return False


def owned_files(
    out: Path, profile: str, link: str, force: bool
) -> tuple[list[str], dict[str, str]]:
    """The files (relative to ``out``) of the publication that ``out`` holds and its
    figures' digests (name -> digest, :func:`draw_figures`), after making sure this one may
    replace it: one of ``profile`` from the results at ``link`` (relative to ``out``).
    Raises :class:`PublishRefused` saying why, and what ``force`` would replace, for a
    board of another profile or results folder, or for a folder with a board no
    publication recorded."""
    manifest_path = out / MANIFEST
    if manifest_path.exists():
        manifest = json.loads(manifest_path.read_text())
        previous, reasons = list(manifest["files"]), []
        figures_drawn = manifest.get("figures", {})
        if manifest["profile"] != profile:
            reasons.append(f"its board is of profile {manifest['profile']!r} (this is {profile!r})")
        if (out / manifest["results"]).resolve() != (out / link).resolve():
            reasons.append(
                f"its board was made from the results in {out / manifest['results']} (these "
                f"are in {out / link})"
            )
    else:
        previous = [name for name in ("README.md", "index.html") if (out / name).exists()]
        reasons, figures_drawn = [], {}
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
    return previous, figures_drawn


def draw_figures(
    summary: pd.DataFrame,
    results_dir: Path,
    profile: str,
    out: Path,
    tracks: dict[str, pd.DataFrame] | None = None,
    drawn: dict[str, str] | None = None,
) -> dict[str, str]:
    """Draw every figure into ``out/figures`` (PNG and SVG), with a progress bar; returns
    each figure's name -> digest (:func:`figure_digest`), in drawing order.

    ``summary`` is the paper track's; each of ``tracks`` (name -> summary) gets its own
    heat map. A figure whose digest is that of ``drawn`` (the previous publication's) is
    kept as it is.
    """
    drawn = drawn or {}
    kept = kept_estimates(results_dir, profile)
    drawings = [("relative-rmse", functools.partial(figures.relative_rmse_heatmap, summary))]
    for name, of_track in (tracks or {}).items():
        drawings.append(
            (
                f"relative-rmse-{name}",
                functools.partial(figures.relative_rmse_heatmap, of_track, f"Track {name}: "),
            )
        )
        if settles(name):  # where the first test trajectory starts matters: draw it
            drawings += _track_trajectories(name, results_dir, profile)
    drawings.append(("cost-accuracy", functools.partial(figures.cost_accuracy_figure, summary)))
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
    directory, digests = out / "figures", {}
    for name, draw in tqdm(drawings, desc="drawing figures", unit="figure", disable=None):
        inputs = _inputs_digest(draw)
        digests[name] = figure_digest(inputs, directory / name)
        if digests[name] != drawn.get(name):
            figures.save(draw(), directory / name)
            digests[name] = figure_digest(inputs, directory / name)
    return digests


def figure_digest(inputs: str, path_without_suffix: Path) -> str:
    """``<inputs>-<files>``: the digest of a figure's inputs and of its PNG and SVG files
    as they are now (``missing`` for a file that is not there)."""
    files = hashlib.sha256()
    for suffix in (".png", ".svg"):
        path = path_without_suffix.with_suffix(suffix)
        files.update(path.read_bytes() if path.is_file() else b"missing")
    return f"{inputs}-{files.hexdigest()[:16]}"


def _inputs_digest(draw: functools.partial) -> str:
    """A digest of what ``draw`` draws from: its function and arguments, the code of this
    package that its module imports (not the estimators' or systems': a change to those
    reaches a figure through its arguments) and matplotlib's version. Pickling the same
    data twice gives the same bytes; where it would not, the figure is only drawn again."""
    import matplotlib

    function = draw.func
    code = imported_code_digest(function.__module__)
    digest = hashlib.sha256(f"{code}-matplotlib{matplotlib.__version__}".encode())
    payload = (function.__module__, function.__qualname__, draw.args, draw.keywords)
    digest.update(pickle.dumps(payload, protocol=5))
    return digest.hexdigest()[:16]


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
