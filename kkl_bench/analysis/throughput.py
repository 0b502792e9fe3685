"""Training throughput: what each learned row's training achieves on this machine.

For a learned row and a system, the row's fit runs at a profile's sizes (its networks,
batches, windows and data) with every training, each
:func:`~kkl_bench.kkl.optimize.minimize` call, measured instead of run to the end
(:func:`~kkl_bench.kkl.optimize.probing`): one optimizer step counted (the matrix
products of the loss and its gradient, :mod:`kkl_bench.support.flops`), then ``steps`` steps
timed. Per training, one row: samples per second, matrix-product flops per second, and
those over the float32 peak of the device it trained on, measured in the same run
(:func:`kkl_bench.analysis.cost.peak_gflops`, protocol 6.3). The fit runs from an empty
temporary cache, so nothing it trains is kept or reused. It trains on the CPU, where the
board's fits train, unless asked for another device (``device``, recorded per row).

:func:`measure` merges its rows into a CSV (one row per estimator, system, training and
code commit); :func:`throughput_table` sums each fit's trainings and shows the newest
measurement of each fit, with the share of the peak an earlier commit's measurement
reached beside it (a speed-up's before and after). Protocol 6.5 shows the table.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kkl_bench import families, variants
from kkl_bench.analysis.cost import peak_gflops
from kkl_bench.kkl.optimize import probing
from kkl_bench.registry import estimators
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import Profile
from kkl_bench.support.devices import resolve
from kkl_bench.support.executors import thread_limit
from kkl_bench.support.provenance import provenance

THROUGHPUT_FILE = "training-throughput.csv"
KEY = ["estimator", "system", "training", "device", "git_commit"]
FIT_KEY = ["estimator", "system", "device", "git_commit"]
COLUMNS = [
    *KEY[:3],
    "samples_per_step",
    "fit_steps",
    "steps",
    "seconds",
    "samples_per_s",
    "flops_per_step",
    "gflops_per_s",
    "peak_gflops",
    "of_peak",
    "profile",
    "threads",
    "device",
    "git_commit",
]
"""What a measurement stores per training: ``fit_steps`` the optimizer steps the fit
runs, ``seconds`` ``steps`` times the median of as many timed ones (a compiled
training's compiles left out, :class:`~kkl_bench.kkl.optimize.Probe`),
``flops_per_step`` the matrix products of one (forward and backward), ``gflops_per_s``
their rate, ``of_peak`` that over ``peak_gflops`` (float32, same run, same ``device``:
``cpu`` on ``threads`` threads, or ``cuda``)."""


def learned() -> list[str]:
    """Every installed estimator of the ``learned`` family."""
    return [
        name
        for name in estimators.names()
        if families.estimator_family(estimators.get(name)) == "learned"
    ]


def probe_fit(
    estimator: str, system: str, profile: Profile, steps: int, seed: int = 0, device: str = "cpu"
) -> list[dict] | None:
    """One record per training of ``estimator``'s fit for ``system`` at ``profile``'s sizes
    (from an empty cache, trained on ``device``): the
    :class:`~kkl_bench.kkl.optimize.Probe` records of the trainings of one description
    summed (a curriculum's stages), ``flops_per_step`` and ``samples_per_step`` their means
    over the timed steps. None if the estimator does not support the system."""
    with tempfile.TemporaryDirectory() as cache, probing(steps) as probe:
        spec = RunSpec((estimator,), (system,), None, profile, cache_dir=Path(cache), device=device)
        context = make_fit_context(spec, estimator, system, seed)
        model = variants.build(estimator)
        if model.unsupported_reason(context.system, context.measurement) is not None:
            return None
        model.fit(context)
    records = pd.DataFrame(probe.records)
    records["flops"] = records["flops_per_step"] * records["steps"]
    records["samples"] = records["samples_per_step"] * records["steps"]
    summed = records.groupby("training", sort=False)[
        ["fit_steps", "steps", "seconds", "flops", "samples"]
    ].sum()
    summed["flops_per_step"] = summed.pop("flops") / summed["steps"]
    summed["samples_per_step"] = summed.pop("samples") / summed["steps"]
    return summed.reset_index().to_dict("records")


def measure(
    estimators: Sequence[str],
    systems: Sequence[str],
    profile: Profile,
    out: Path,
    steps: int = 20,
    threads: int = 1,
    device: str = "cpu",
) -> pd.DataFrame:
    """Measure every training of every (estimator, system) on ``device`` (``cpu`` on
    ``threads`` threads, ``cuda`` or ``auto``: :func:`kkl_bench.support.devices.resolve`,
    a ``ValueError`` before any work where it cannot) and merge the rows into ``out`` (CSV,
    :data:`COLUMNS`), written after each fit so an interrupted run keeps what it measured;
    a row of the same key (this code's commit, the same device) is replaced. Returns this
    run's rows."""
    device = resolve(device)
    commit = provenance()["git_commit"]
    rows = []
    with thread_limit(threads):
        peak = peak_gflops("float32", threads, device=device)
        for estimator, system in tqdm(
            [(e, s) for e in estimators for s in systems], desc="training throughput", unit="fit"
        ):
            for record in probe_fit(estimator, system, profile, steps, device=device) or ():
                rate = record["flops_per_step"] * record["steps"] / record["seconds"] / 1e9
                rows.append(
                    {
                        "estimator": variants.canonical(estimator),
                        "system": system,
                        **record,
                        "samples_per_s": record["samples_per_step"]
                        * record["steps"]
                        / record["seconds"],
                        "gflops_per_s": rate,
                        "peak_gflops": peak,
                        "of_peak": rate / peak,
                        "profile": profile.name,
                        "threads": threads,
                        "device": device,
                        "git_commit": commit,
                    }
                )
            _merge(out, pd.DataFrame(rows, columns=COLUMNS))
    return pd.DataFrame(rows, columns=COLUMNS)


def _merge(out: Path, rows: pd.DataFrame) -> None:
    stored = read_throughput(out)
    if stored is not None:
        kept = stored.merge(rows[KEY], on=KEY, how="left", indicator=True)["_merge"] == "left_only"
        rows = pd.concat([stored[kept.to_numpy()], rows], ignore_index=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows.to_csv(out, index=False)


def read_throughput(path: Path) -> pd.DataFrame | None:
    """The rows :func:`measure` wrote to ``path``, or None if there is no such file;
    ``ValueError`` naming the file and the missing columns if it is not a measurement.
    A file from before rows recorded their device reads ``cpu``: this project's were
    measured on machines without a GPU."""
    if not path.exists():
        return None
    frame = pd.read_csv(path, dtype={"git_commit": str})
    if "device" not in frame.columns:
        frame["device"] = "cpu"
    missing = [column for column in COLUMNS if column not in frame.columns]
    if missing:
        raise ValueError(f"{path} is not a training-throughput measurement: no {missing}")
    return frame[COLUMNS]


FIT_COLUMNS = [
    *FIT_KEY,
    "trainings",
    "optimizer_s",
    "gflops_per_s",
    "of_peak",
    "longest",
    "longest_share",
    "longest_samples_per_s",
    "longest_of_peak",
]


def fit_throughput(frame: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, system, git_commit), the fit's trainings taken together, each for the
    steps the fit runs: ``optimizer_s`` the time their optimizer steps take, ``gflops_per_s``
    and ``of_peak`` their products' rate, and the training that takes longest
    (``longest``, its ``longest_share`` of the time, ``longest_samples_per_s``)."""
    frame = frame.assign(
        fit_s=frame["fit_steps"] * frame["seconds"] / frame["steps"],
        fit_flops=frame["fit_steps"] * frame["flops_per_step"],
    )
    rows = []
    for key, fit in frame.groupby(FIT_KEY, sort=False):
        longest = fit.loc[fit["fit_s"].idxmax()]
        rate = fit["fit_flops"].sum() / fit["fit_s"].sum() / 1e9
        rows.append(
            {
                **dict(zip(FIT_KEY, key, strict=True)),
                "trainings": len(fit),
                "optimizer_s": fit["fit_s"].sum(),
                "gflops_per_s": rate,
                "of_peak": rate / fit["peak_gflops"].iloc[0],
                "longest": longest["training"],
                "longest_share": longest["fit_s"] / fit["fit_s"].sum(),
                "longest_samples_per_s": longest["samples_per_s"],
                "longest_of_peak": longest["of_peak"],
            }
        )
    return pd.DataFrame(rows, columns=FIT_COLUMNS)


def throughput_table(frame: pd.DataFrame) -> pd.DataFrame:
    """The table protocol 6.5 shows: per (estimator, system, device), in the order
    measured, the newest measurement's :func:`fit_throughput`, and ``Before``: the share of
    the peak of the measurement of another commit on that device before it, if any (a
    speed-up's before)."""
    fits = fit_throughput(frame)
    row = ["estimator", "system", "device"]
    latest = fits.drop_duplicates(row, keep="last")
    before = fits.drop(latest.index).drop_duplicates(row, keep="last")
    before = before.set_index(row)["of_peak"]
    return pd.DataFrame(
        {
            "Row": latest["estimator"],
            "System": latest["system"],
            "Device": latest["device"],
            "Trainings": latest["trainings"],
            "Optimizer time of a fit (s)": latest["optimizer_s"].map("{:.0f}".format),
            "GFLOP/s": latest["gflops_per_s"].map("{:.3g}".format),
            "Of peak": latest["of_peak"].map("{:.1%}".format),
            "Before": [
                f"{before[key]:.1%}" if key in before.index else "-"
                for key in zip(*(latest[column] for column in row), strict=True)
            ],
            "Longest training": [
                f"{name.split(': ', 1)[-1]} ({share:.0%}; {rate:.3g} samples/s, {peak:.1%})"
                for name, share, rate, peak in zip(
                    latest["longest"],
                    latest["longest_share"],
                    latest["longest_samples_per_s"],
                    latest["longest_of_peak"],
                    strict=True,
                )
            ],
            "Commit": latest["git_commit"].str[:7],
        }
    ).reset_index(drop=True)


def render(frame: pd.DataFrame) -> str:
    """:func:`throughput_table` as the GitHub table protocol 6.5 shows."""
    return tabulate(
        throughput_table(frame),
        headers="keys",
        tablefmt="github",
        showindex=False,
        disable_numparse=True,
    )
