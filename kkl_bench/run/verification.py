"""``kkl-bench verify``: re-derive published cells at the current commit and say whether
each number stands (protocol 9).

A cell is recomputed by the harness as ``kkl-bench run`` made it (its row, system, track,
task, profile and seed), into a temporary results folder with an empty model cache, so
nothing cached or published is read. Its per-trajectory RMSE is then compared with the
published one: *identical* (every trajectory bit for bit), *within tolerance* (the largest
per-trajectory relative difference at most :data:`TOLERANCE`) or *drifted*. Each verdict is
appended to ``verification.csv`` in the board's folder as soon as it is known, with the
commits and the likely cause of a drift; the board's Reproduce section reads the latest
run from there.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
from filelock import FileLock

from kkl_bench.registry import did_you_mean
from kkl_bench.run import harness
from kkl_bench.run.results import (
    CellResult,
    cell_path,
    estimate_path,
    phase_seconds,
    read_cell,
    scoring_seconds,
    trained_models,
)
from kkl_bench.run.spec import RunSpec
from kkl_bench.suite.task import get_profile
from kkl_bench.suite.tracks import get_track
from kkl_bench.support.executors import execute
from kkl_bench.support.provenance import provenance

VERIFICATION_FILE = "verification.csv"
"""The verdicts of every ``kkl-bench verify`` run, in the board's folder (appended)."""
TOLERANCE = 1e-4
"""Default largest relative difference of a trajectory's RMSE for *within tolerance*: a
hundredth of a percent, below the board's three significant digits and above the float
reordering of a different thread count (protocol 9)."""
IDENTICAL, WITHIN, DRIFTED = "identical", "within tolerance", "drifted"
VERDICTS = (IDENTICAL, WITHIN, DRIFTED)
COLUMNS = [
    "run",
    "cell",
    "estimator",
    "system",
    "track",
    "regime",
    "seed",
    "verdict",
    "largest_relative_difference",
    "tolerance",
    "cause",
    "published_commit",
    "verified_commit",
    "selection",
    "seconds",
    "replaced",
]


class VerifyError(ValueError):
    """A cell to verify that does not exist or is not a cell of the results."""


def cell_files(results_dir: Path, profile: str) -> list[Path]:
    """Every cell record of ``profile`` under ``results_dir``, sorted."""
    root = Path(results_dir) / profile
    return sorted(path for path in root.rglob("*.json") if ".claims" not in path.parts)


def named_cells(results_dir: Path, profile: str, names: Sequence[str]) -> list[Path]:
    """The records of ``names``: paths relative to ``<results_dir>/<profile>`` with or
    without ``.json`` (``ekf/duffing/sinusoid-seed0``, ``ekf/vdp/hard/outliers-seed0``)."""
    root = Path(results_dir) / profile
    paths = []
    for name in names:
        path = root / (name if name.endswith(".json") else f"{name}.json")
        if not path.is_file():
            known = [
                p.relative_to(root).with_suffix("").as_posix()
                for p in cell_files(results_dir, profile)
            ]
            raise VerifyError(
                f"no cell {name!r} in {root}/ (name a record by its path there, e.g. "
                f"ekf/duffing/sinusoid-seed0 or ekf/vdp/hard/outliers-sinusoid-seed0)"
                f"{did_you_mean(name.removesuffix('.json'), known)}"
            )
        paths.append(path)
    return paths


def sampled_cells(paths: Sequence[Path], n: int, seed: int) -> list[Path]:
    """``n`` of ``paths`` drawn without replacement by ``seed`` (all if fewer)."""
    chosen = np.random.default_rng(seed).choice(len(paths), min(n, len(paths)), replace=False)
    return [paths[i] for i in sorted(chosen)]


def recompute(cell: CellResult, work: Path, command: str | None = None) -> tuple[CellResult, Path]:
    """``cell`` scored again at the current code, into ``work/results`` with the model cache
    ``work/cache`` (left as it is: empty at the start of a verification run); returns the
    new record and its path. Only the cell's own row is fitted (a ``run`` of its estimator
    would also fit its ``+logged`` or ``+truth`` rows on the task)."""
    spec = RunSpec(
        estimators=(cell.estimator,),
        systems=(cell.system,),
        regimes=(cell.regime,),
        tracks=(cell.track,),
        profile=get_profile(cell.profile),
        seeds=(cell.seed,),
        results_dir=work / "results",
        cache_dir=work / "cache",
        force=True,
        device="cpu",
        command=command,
    )
    tasks = tuple(task for task in spec.tasks(cell.system) if task.regime == cell.regime)
    harness.run_job(spec, harness.Job(cell.estimator, cell.system, tasks, cell.seed))
    path = cell_path(
        spec.results_dir, cell.estimator, cell.system, cell.regime, cell.profile, cell.seed,
        cell.track,
    )  # fmt: skip
    return read_cell(path), path


def estimated_seconds(cells: Sequence[CellResult]) -> list[float]:
    """Each of ``cells``' processor seconds to recompute it in one :func:`verify` run,
    estimated from its own record as ``kkl-bench regenerate`` estimates a job: the
    training its fit recorded (:func:`~kkl_bench.run.results.phase_seconds`) plus its
    scoring. The recomputations share one model cache, so a model a cell shares with an
    earlier one of ``cells`` (:func:`~kkl_bench.run.results.trained_models`: a Phase-1
    model under several KKL rows, one model scored on several tracks) is counted at the
    earlier cell only; a fit that caches nothing (a filter's) is counted at each."""
    trained: set[tuple] = set()
    estimates = []
    for cell in cells:
        cached = trained_models(cell)
        fit = 0.0
        for phase, seconds in phase_seconds(cell).items():
            model = (cell.system, cell.seed, phase, seconds)
            if model in trained:
                continue
            if model in cached:
                trained.add(model)
            fit += seconds
        task = get_track(cell.track).task(cell.regime, cell.system)
        estimates.append(fit + scoring_seconds(cell, task.n_samples))
    return estimates


def largest_relative_difference(published: Sequence[float], recomputed: Sequence[float]) -> float:
    """The largest ``|b - a| / |a|`` over the trajectories' RMSEs ``a`` (published) and ``b``
    (recomputed): 0 where both are equal or both non-finite (a diverged trajectory stays
    diverged), infinite where only one is finite or the trajectory counts differ."""
    a, b = np.asarray(published, dtype=float), np.asarray(recomputed, dtype=float)
    if a.shape != b.shape:
        return math.inf
    if not a.size:
        return 0.0
    same = (a == b) | (~np.isfinite(a) & ~np.isfinite(b))
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.where(same, 0.0, np.abs(b - a) / np.abs(a))
    relative = np.where(np.isnan(relative), math.inf, relative)
    return float(relative.max())


def verdict_of(
    published: CellResult, recomputed: CellResult, tolerance: float
) -> tuple[str, float]:
    """The verdict on ``published`` and the largest per-trajectory relative difference."""
    if published.status != recomputed.status:
        return DRIFTED, math.inf
    if published.rmse == recomputed.rmse:
        return IDENTICAL, 0.0
    difference = largest_relative_difference(published.rmse, recomputed.rmse)
    return (WITHIN if difference <= tolerance else DRIFTED), difference


BUDGET = ("steps", "samples")
"""What a fit report's ``spent`` says of the training budget, per phase (the rest of it,
the seconds, device and commit, differs from one training to the next)."""


def training_budget(fit_report: dict) -> dict:
    """The steps and samples each training phase of ``fit_report`` spent (:data:`BUDGET`)."""
    spent = fit_report.get("spent") or {}
    return {
        phase: {key: record.get(key) for key in BUDGET}
        for phase, record in spent.items()
        if isinstance(record, dict)
    }


def cause_of(published: CellResult, recomputed: CellResult) -> str:
    """What differs between how the two records were made, as far as they say: the status,
    the test set, the training spent or the chosen settings; empty if nothing they record
    differs."""
    if published.status != recomputed.status:
        reason = recomputed.error.splitlines()[-1] if recomputed.error else ""
        return f"status {published.status} -> {recomputed.status}" + (
            f" ({reason})" if reason else ""
        )
    if published.test_set_fingerprint != recomputed.test_set_fingerprint:
        return "other test trajectories"
    before, after = published.fit_report, recomputed.fit_report
    if training_budget(before) != training_budget(after):
        return "another training budget (fit_report.spent differs)"
    changed = sorted(
        key
        for key in set(before) | set(after)
        if key != "spent" and before.get(key) != after.get(key)
    )
    if changed:
        return "fit report differs in " + ", ".join(changed)
    return ""


def _replace(published_path: Path, recomputed_path: Path) -> None:
    """Put the recomputed record (and its kept estimate) in place of the published one,
    each by an atomic rename."""
    for source, target in (
        (estimate_path(recomputed_path), estimate_path(published_path)),
        (recomputed_path, published_path),
    ):
        if source.exists():
            temporary = target.with_name(f".{target.name}.verify.tmp")
            shutil.copyfile(source, temporary)
            os.replace(temporary, target)
        else:
            target.unlink(missing_ok=True)


def append(out_file: Path, rows: pd.DataFrame) -> None:
    """Append ``rows`` to the verification file (created with its header), under a lock."""
    out_file.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(out_file.with_name(f".{out_file.name}.lock")):  # hidden, ignored by git
        rows[COLUMNS].to_csv(out_file, mode="a", header=not out_file.exists(), index=False)


def read_verifications(path: Path) -> pd.DataFrame | None:
    """Every verdict in ``path``, or None if there is no such file."""
    if not Path(path).exists():
        return None
    return pd.read_csv(path, keep_default_na=False, na_values={"largest_relative_difference": []})


def latest_run(verifications: pd.DataFrame) -> pd.DataFrame:
    """The verdicts of the most recent run in ``verifications``."""
    return verifications[verifications["run"] == verifications["run"].max()]


def run_to_resume(out_file: Path, selection: str) -> tuple[str, set[str]]:
    """``(run, cells)``: the latest run recorded in ``out_file`` and the cells it has verdicts
    for, to go on with an interrupted run of the same ``selection``. Raises
    :class:`VerifyError` if there is no run or the latest chose its cells otherwise."""
    verifications = read_verifications(Path(out_file))
    if verifications is None or verifications.empty:
        raise VerifyError(f"--resume: no verification run in {out_file} to go on with")
    latest = latest_run(verifications)
    recorded = latest["selection"].iloc[0]
    if recorded != selection:
        raise VerifyError(
            f"--resume: the latest run ({latest['run'].iloc[0]}) chose {recorded!r}, this one "
            f"{selection!r}; give the same cells or --sample and --sample-seed to go on with it"
        )
    return latest["run"].iloc[0], set(latest["cell"])


def _recompute_timed(path: Path, work: Path, command: str | None) -> tuple:
    """``(path, published, recomputed, its path, seconds)`` for the record at ``path``
    (:func:`recompute`; a job of :func:`verify`, run in a worker when ``jobs > 1``)."""
    published = read_cell(path)
    start = time.perf_counter()
    recomputed, new_path = recompute(published, work, command)
    return path, published, recomputed, new_path, time.perf_counter() - start


def verify(
    paths: Iterable[Path],
    results_dir: Path,
    out_file: Path,
    selection: str,
    work: Path,
    tolerance: float = TOLERANCE,
    replace_drifted: bool = False,
    command: str | None = None,
    on_cell: Callable[[dict], None] | None = None,
    jobs: int = 1,
    run: str | None = None,
) -> pd.DataFrame:
    """Recompute each cell record of ``paths`` (under ``results_dir``) in the empty folder
    ``work`` (results and model cache, :func:`recompute`; ``jobs`` cells at a time, in
    worker processes that share the cache, never two that need one model not trained
    yet: :func:`~kkl_bench.run.results.trained_models`), append each verdict to
    ``out_file`` as soon as it is known and return them all.

    ``selection`` says how the cells were chosen (recorded with each verdict). With
    ``replace_drifted`` a drifted cell's record is replaced by the recomputed one.
    ``on_cell(row)`` is called after each cell. ``run`` names the run the verdicts join
    (default a new one, named by the time it starts; :func:`run_to_resume` gives an
    interrupted one); each verdict records the commit that verified it.
    """
    run = run or datetime.now(UTC).isoformat(timespec="seconds")
    commit = provenance()["git_commit"]
    rows = []
    paths = list(paths)
    jobs_arguments = [(path, work, command) for path in paths]
    # two cells of one model (or of KKL rows sharing a Phase-1 model) are not recomputed
    # at once: one would wait on the other's training
    claims = [trained_models(read_cell(path)) for path in paths]
    for path, published, recomputed, new_path, seconds in execute(
        _recompute_timed, jobs_arguments, jobs, claims=claims
    ):
        verdict, difference = verdict_of(published, recomputed, tolerance)
        replaced = replace_drifted and verdict == DRIFTED
        if replaced:
            _replace(path, new_path)
        row = {
            "run": run,
            "cell": path.relative_to(Path(results_dir) / published.profile).as_posix(),
            "estimator": published.estimator,
            "system": published.system,
            "track": published.track,
            "regime": published.regime,
            "seed": published.seed,
            "verdict": verdict,
            "largest_relative_difference": difference,
            "tolerance": tolerance,
            "cause": cause_of(published, recomputed) if verdict != IDENTICAL else "",
            "published_commit": published.provenance.get("git_commit"),
            "verified_commit": commit,
            "selection": selection,
            "seconds": round(seconds, 1),
            "replaced": replaced,
        }
        append(out_file, pd.DataFrame([row]))
        rows.append(row)
        if on_cell is not None:
            on_cell(row)
    return pd.DataFrame(rows, columns=COLUMNS)


def verification_sentence(verifications: pd.DataFrame | None) -> str:
    """What the board says of its latest verification run (``verifications``: the rows of
    :data:`VERIFICATION_FILE`, None if it was never verified), read from the verdicts."""
    if verifications is None or verifications.empty:
        return (
            "Not verified yet: `kkl-bench verify --sample 8` re-derives a random sample of "
            f"cells at the current commit and records the verdicts in `{VERIFICATION_FILE}`."
        )
    latest = latest_run(verifications)
    counts = latest["verdict"].value_counts()
    tolerances = ", ".join(f"{t:g}" for t in sorted(set(latest["tolerance"])))
    drifted = latest[latest["verdict"] == DRIFTED]
    verified_at = sorted(set(latest["verified_commit"].astype(str)))
    commits = ", ".join(f"`{c}`" for c in verified_at)
    sentence = (
        f"Last verified on {latest['run'].iloc[0][:10]} at commit"
        f"{'s' if len(verified_at) > 1 else ''} {commits} by "
        f"`kkl-bench verify`: of the cells it chose ({', '.join(sorted(set(latest['selection'])))}), "
        f"{len(latest)} re-derived from an empty model cache: "
        f"{counts.get(IDENTICAL, 0)} identical, "
        f"{counts.get(WITHIN, 0)} within a relative {tolerances} of every trajectory's RMSE, "
        f"{len(drifted)} drifted"
    )
    if len(drifted):
        largest = drifted["largest_relative_difference"].astype(float).max()
        replaced = int(drifted["replaced"].astype(str).eq("True").sum())
        sentence += f" (largest relative difference {largest:.3g}"
        sentence += f"; {replaced} replaced by the recomputed cell)" if replaced else ")"
    return sentence + "."


VERDICT_COLUMNS = {
    "cell": "Cell",
    "verdict": "Verdict",
    "largest_relative_difference": "Largest relative difference",
    "cause": "Likely cause",
    "published_commit": "Published at",
    "seconds": "Seconds",
}
"""The columns of the board's table of the latest verification run, with their headers."""
