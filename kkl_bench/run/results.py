"""Per-cell result records: written atomically, one JSON file per cell, loaded into pandas.

A *cell* is one (estimator, track, system, regime, profile, seed). Its file holds the
cell's aggregate metrics, the per-trajectory values behind them, the costs,
and the provenance needed to reproduce it. Beside it, a compressed ``.npz``
keeps the truth and the estimate of the first test trajectory, so figures
never need a rerun. Files are written to a temporary name and renamed into
place, so a reader (or a crash) never sees half a file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from filelock import FileLock

from kkl_bench.protocol.metrics import mark_diverged
from kkl_bench.protocol.streams import PAPER_TRACK

RECORD_FORMAT = 3
"""Version of the JSON layout below. Format 2 added ``track`` and ``settling_time_s``,
format 3 ``family``."""
READABLE_FORMATS = (1, 2, 3)
"""Formats :func:`read_cell` reads (a format-1 record is a paper-track cell without
settling times)."""


@dataclass
class CellResult:
    """Everything recorded about one scored cell.

    ``status`` is ``"ok"`` (scored; some trajectories may have diverged),
    ``"unsupported"`` (the estimator cannot be fitted for the task: its measurement
    model, a system it cannot express or cannot afford; ``error`` gives its reason) or
    ``"error"`` (the estimator raised or broke the interface; ``error`` says how). The
    metric fields are empty but for ``"ok"``. ``family`` is the row's
    (:mod:`kkl_bench.families`) when the cell was written; empty in cells written before
    families were recorded.
    """

    estimator: str
    system: str
    regime: str
    task: str
    profile: str
    seed: int
    status: str
    n_test: int
    estimator_params: dict[str, Any] = field(default_factory=dict)
    rmse: list[float] = field(default_factory=list)
    smape: list[float] = field(default_factory=list)
    nrmse: list[float] = field(default_factory=list)
    per_state_rmse: list[list[float]] = field(default_factory=list)
    fit_time_s: float = math.nan
    fit_report: dict[str, Any] = field(default_factory=dict)
    estimate_us_per_step: float = math.nan
    error: str = ""
    protocol: str = ""
    test_set_fingerprint: str = ""
    stream_fingerprint: str = ""
    provenance: dict[str, Any] = field(default_factory=dict)
    track: str = PAPER_TRACK
    settling_time_s: list[float] = field(default_factory=list)
    family: str = ""
    record_format: int = RECORD_FORMAT

    @property
    def n_diverged(self) -> int:
        return sum(not math.isfinite(value) for value in self.rmse)


@dataclass(frozen=True)
class KeptEstimate:
    """One test trajectory kept with its cell: ``t: (steps,)`` in s, truth ``x`` and
    estimate ``x_hat``, both ``(steps, n_x)``. Stored as float32."""

    t: np.ndarray
    x: np.ndarray
    x_hat: np.ndarray


def cell_path(
    results_dir: Path,
    estimator: str,
    system: str,
    regime: str,
    profile: str,
    seed: int,
    track: str = PAPER_TRACK,
) -> Path:
    """Where a cell's record lives under ``results_dir``:
    ``<profile>/<estimator>/<system>/[<track>/]<regime>-seed<seed>.json`` (no track
    folder for the paper track)."""
    folder = Path(results_dir) / profile / estimator / system
    if track != PAPER_TRACK:
        folder = folder / track
    return folder / f"{regime}-seed{seed}.json"


def claim_path(results_dir: Path, estimator: str, system: str, profile: str, seed: int) -> Path:
    """The lock file of :func:`claim` (its job's status file sits beside it, see
    :mod:`kkl_bench.support.status`)."""
    return Path(results_dir) / ".claims" / profile / f"{estimator}--{system}--seed{seed}.lock"


def claim(results_dir: Path, estimator: str, system: str, profile: str, seed: int) -> FileLock:
    """The lock a run holds while it fits ``estimator`` on ``system`` and scores its cells.

    Lock files live in ``<results_dir>/.claims/``, which ignores itself in git
    (removing a released lock file would race with a run about to take it);
    ``filelock`` uses ``fcntl`` locks, which network file systems with lock
    support honour.
    """
    path = claim_path(results_dir, estimator, system, profile, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    (Path(results_dir) / ".claims" / ".gitignore").write_text("*\n")
    return FileLock(path)


def estimate_path(path: Path) -> Path:
    """Where the kept estimate of the cell recorded at ``path`` lives."""
    return Path(path).with_suffix(".npz")


def write_cell(results_dir: Path, cell: CellResult, kept: KeptEstimate | None = None) -> Path:
    """Write ``cell`` (and ``kept`` beside it, first) atomically; returns the record's path.

    Without ``kept`` a stale estimate file of an earlier run is removed.
    """
    path = cell_path(
        results_dir, cell.estimator, cell.system, cell.regime, cell.profile, cell.seed, cell.track
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    if kept is None:
        estimate_path(path).unlink(missing_ok=True)
    else:
        arrays = {name: np.asarray(value, np.float32) for name, value in asdict(kept).items()}
        _write_atomic(estimate_path(path), lambda file: np.savez_compressed(file, **arrays))
    text = json.dumps(_to_json(asdict(cell)), indent=1, allow_nan=False)
    _write_atomic(path, lambda file: file.write(text.encode()))
    return path


def read_estimate(path: Path) -> KeptEstimate | None:
    """The kept estimate of the cell recorded at ``path``, or None if it has none."""
    stored = estimate_path(path)
    if not stored.exists():
        return None
    with np.load(stored) as arrays:
        return KeptEstimate(**{name: arrays[name].astype(float) for name in arrays.files})


def _write_atomic(path: Path, write: Callable[[Any], Any]) -> None:
    """Call ``write(binary_file)`` on a temporary file, then rename it to ``path``.

    If anything fails part-way (a full disk, say) the temporary file is
    removed, ``path`` is left as it was, and the ``OSError`` names ``path``.
    """
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(handle, 0o666 & ~_umask())  # mkstemp makes 0600; results are shared files
        with os.fdopen(handle, "wb") as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except OSError as error:
        Path(temporary).unlink(missing_ok=True)
        raise OSError(error.errno, f"could not write {path}: {error.strerror or error}") from error
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_writable(results_dir: Path) -> None:
    """Create ``results_dir`` if needed and make sure files can be written there.

    Raises ``OSError`` naming the directory, before any work is done.
    """
    results_dir = Path(results_dir)
    try:
        results_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=results_dir):
            pass
    except OSError as error:
        raise OSError(
            f"results directory {results_dir} is not writable: {error.strerror or error}"
        ) from error


class DamagedCellError(ValueError):
    """A cell file that cannot be read, does not match the record schema, or is of an
    older record format. ``path`` and ``reason`` say which and why."""

    def __init__(self, path: Path, reason: str) -> None:
        self.path, self.reason = Path(path), reason
        super().__init__(f"damaged result file {path}: {reason}")


_FIELDS = {f.name: f for f in dataclasses.fields(CellResult)}
_LISTS = ("rmse", "smape", "nrmse", "per_state_rmse", "settling_time_s")


def read_cell(path: Path) -> CellResult:
    """Load one record written by :func:`write_cell`.

    Raises :class:`DamagedCellError` naming the file and the reason if it is
    not whole JSON, not a record of this schema, or of another record format.
    """
    try:
        data = _from_json(json.loads(Path(path).read_bytes()))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedCellError(path, f"not valid JSON ({error}); truncated or corrupted") from None
    if not isinstance(data, dict):
        raise DamagedCellError(path, f"expected a JSON object, found {type(data).__name__}")
    record_format = data.get("record_format", RECORD_FORMAT)
    if record_format not in READABLE_FORMATS:
        raise DamagedCellError(
            path,
            f"record format {record_format!r}, this kkl-bench reads formats "
            f"{', '.join(map(str, READABLE_FORMATS))}; "
            "rerun the cell (`kkl-bench run` recomputes it) or read it with the kkl-bench "
            "version that wrote it",
        )
    required = {
        name for name, f in _FIELDS.items() if f.default is MISSING and f.default_factory is MISSING
    }
    missing, unknown = sorted(required - set(data)), sorted(set(data) - set(_FIELDS))
    if missing or unknown:
        reason = "; ".join(
            text
            for text in (
                missing and f"missing fields {', '.join(missing)}",
                unknown and f"unknown fields {', '.join(unknown)}",
            )
            if text
        )
        raise DamagedCellError(path, reason)
    if not all(isinstance(data.get(name, []), list) for name in _LISTS):
        raise DamagedCellError(path, f"fields {', '.join(_LISTS)} must be lists")
    return CellResult(**data)


def move_aside(path: Path) -> Path:
    """Rename a damaged cell file (and its kept estimate) to ``<name>.corrupt``; returns the new path."""
    aside = path.with_name(path.name + ".corrupt")
    os.replace(path, aside)
    if estimate_path(path).exists():
        os.replace(
            estimate_path(path),
            estimate_path(path).with_name(estimate_path(path).name + ".corrupt"),
        )
    return aside


def load_results(
    results_dir: Path,
    damaged: list[DamagedCellError] | None = None,
    profile: str | None = None,
) -> pd.DataFrame:
    """Every cell under ``results_dir`` (of ``profile`` only, if given), of every track, as
    one row (per-trajectory values as list columns).

    Columns: the :class:`CellResult` fields, plus ``rmse_mean``, ``rmse_std``,
    ``smape_mean``, ``smape_std``, ``nrmse_mean``, ``nrmse_std`` and
    ``n_diverged``. A trajectory diverged by the protocol's rule scores ``inf``
    (:func:`~kkl_bench.protocol.metrics.mark_diverged`, applied here to cells stored
    before the rule bounded the error too). The means are ``inf`` when any trajectory
    diverged. A
    damaged file raises :class:`DamagedCellError`, or, if a ``damaged`` list
    is given, is appended to it and left out.
    """
    rows = []
    root = Path(results_dir)
    folder = profile or "*"
    paths = [*root.glob(f"{folder}/*/*/*.json"), *root.glob(f"{folder}/*/*/*/*.json")]
    for path in sorted(paths):
        try:
            cell = read_cell(path)
        except DamagedCellError as error:
            if damaged is None:
                raise
            damaged.append(error)
            continue
        # a shallow copy (the record is read for this row only); cells stored before the
        # bound was applied are marked here
        row = mark_diverged(dict(vars(cell)))
        for metric in ("rmse", "smape", "nrmse"):
            row[f"{metric}_mean"], row[f"{metric}_std"] = mean_and_std(row[metric])
        row["n_diverged"] = sum(not math.isfinite(value) for value in row["rmse"])
        rows.append(row)
    return pd.DataFrame(rows)


def training_seconds(report: object) -> float | None:
    """Seconds of every training a fit used, from its fit report's ``spent`` (each phase's
    :func:`recorded_seconds`, stored with the trained model, so a phase loaded from the cache
    counts as long as it took to train). None if the report has no ``spent`` (the
    estimator does not train); NaN if a phase that trained has no recorded time."""
    spent = report.get("spent") if isinstance(report, dict) else None
    if not spent:
        return None
    return sum(
        recorded_seconds(phase) if phase.get("steps", 0) else 0.0 for phase in spent.values()
    )


def fit_seconds(report: object, fit_time_s: float) -> float:
    """The fit time a board shows for a cell (s): :func:`training_seconds` of its fit
    report where the fit trained (so a model loaded from the cache counts as long as it
    took to train, and a shared Phase 1 counts in every row that uses it; NaN if a phase
    recorded no time), else ``fit_time_s``, the wall time of a fit that trains nothing."""
    trained = training_seconds(report)
    return trained if trained else float(fit_time_s)


def mean_fit_seconds(cells: pd.DataFrame) -> float:
    """Mean of :func:`fit_seconds` over ``cells`` (NaN for none)."""
    reports = cells["fit_report"] if "fit_report" in cells else [None] * len(cells)
    seconds = list(map(fit_seconds, reports, cells["fit_time_s"]))
    return float(np.mean(seconds)) if seconds else math.nan


def records_processor_time(phase: dict) -> bool:
    """Whether one training phase (a record of a fit report's ``spent``) trained on the
    CPU and recorded its processor time (its core-seconds, whatever else ran on the
    machine), which :func:`recorded_seconds` then reads instead of its wall time."""
    return phase.get("device", "cpu") == "cpu" and "processor_seconds" in phase


def recorded_seconds(phase: dict) -> float:
    """The time one training phase took (s; a record of a fit report's ``spent``): its
    processor time where it recorded it (:func:`records_processor_time`), else its wall
    time; NaN if it recorded neither."""
    if records_processor_time(phase):
        return phase["processor_seconds"]
    return phase.get("seconds", math.nan)


def phase_seconds(cell) -> dict[str, float]:
    """The time each phase of the fit behind ``cell`` trained for (``fit_report``'s
    ``spent``, stored with the models: :func:`recorded_seconds`); a fit that trained
    nothing, its fit time."""
    report = cell.fit_report if isinstance(cell.fit_report, dict) else {}
    spent = report.get("spent") or {}
    phases = {
        phase: _seconds_or_zero(recorded_seconds(record))
        for phase, record in spent.items()
        if isinstance(record, dict)
    }
    if any(phases.values()):
        return phases
    return {"fit": _seconds_or_zero(cell.fit_time_s)}


def scoring_seconds(cell, samples: int) -> float:
    """The time ``cell``'s estimate of its test set took: its µs per trajectory-step times
    its trajectories and the ``samples`` of each (its task's); 0 where not recorded."""
    per_step = cell.estimate_us_per_step
    if not (isinstance(per_step, float) and math.isfinite(per_step)):
        return 0.0
    return per_step * 1e-6 * cell.n_test * samples


def _seconds_or_zero(value: object) -> float:
    """``value`` if a finite number of seconds, else 0 (nothing recorded)."""
    return float(value) if isinstance(value, float | int) and math.isfinite(value) else 0.0


def trained_models(cell) -> frozenset[tuple]:
    """The trained models behind ``cell``, each named ``(system, seed, phase, seconds it
    trained)`` from its fit report's ``spent`` (the phases that took steps, at their
    :func:`recorded_seconds`): a model several cells share (a Phase-1 model the KKL rows
    load, one model scored on several tracks) is stored with its training record, so it
    reads the same name in each. A fit that trains nothing (a filter's) names none."""
    report = cell.fit_report if isinstance(cell.fit_report, dict) else {}
    spent = report.get("spent") or {}
    return frozenset(
        (cell.system, cell.seed, phase, seconds)
        for phase, record in spent.items()
        if isinstance(record, dict)
        and record.get("steps", 0)
        and math.isfinite(seconds := recorded_seconds(record))
    )


def mean_and_std(values: list[float]) -> tuple[float, float]:
    """Mean and population standard deviation; ``(inf, inf)`` if any value is not finite,
    ``(nan, nan)`` for no values."""
    if not values:
        return math.nan, math.nan
    if not all(math.isfinite(value) for value in values):
        return math.inf, math.inf
    array = np.asarray(values, dtype=float)
    return float(array.mean()), float(array.std())


def _to_json(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {key: _to_json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_to_json(item) for item in value]
    return value


def _from_json(value: Any) -> Any:
    if value in ("inf", "-inf", "nan"):
        return float(value)
    if isinstance(value, dict):
        return {key: _from_json(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_from_json(item) for item in value]
    return value


def kept_estimates(
    results_dir: Path, profile: str, track: str = PAPER_TRACK
) -> dict[tuple[str, str, str], KeptEstimate]:
    """``(estimator, system, regime) -> KeptEstimate`` of ``track``'s cells, from the lowest
    seed that kept one."""
    kept = {}
    pattern = "*/*/*.json" if track == PAPER_TRACK else f"*/*/{track}/*.json"
    for path in sorted(Path(results_dir, profile).glob(pattern)):
        regime, _, seed = path.stem.rpartition("-seed")
        folder = path.parent if track == PAPER_TRACK else path.parent.parent
        key = (folder.parent.name, folder.name, regime)
        if key in kept and kept[key][0] <= int(seed):
            continue
        estimate = read_estimate(path)
        if estimate is not None:
            kept[key] = (int(seed), estimate)
    return {key: estimate for key, (_, estimate) in kept.items()}
