"""What stopping earlier would have saved the refit, replayed exactly on its recorded curves.

Protocol 6.5's plateau rule halves a training's learning rate at each plateau and stops at
the plateau after the fifth halving, keeping the state of its lowest validation error. A
rule that only ever stops a training *sooner* needs no new training to judge: up to the
step where it would stop, the training is the one the refit ran, so the state it would
keep is the best of the recorded curve up to that step. Two such rules are replayed on
every training the refit has finished so far, each once (a training is known by its system,
seed, path in the fit report and curve: every KKL row of a system and seed shares Phase 1's,
and a variant that only uses a row's networks differently online reports its row's):

- ``after k halvings`` (k = 0..4): stop at the plateau that follows the k-th halving,
  that is at the step of the (k+1)-th, instead of the sixth plateau (k = 0: at the first
  plateau, the learning rate never lowered);
- ``give up at the first plateau``: stop at the first plateau when no measurement since
  the start has been below the training's starting error, so the state it started from
  is kept (a curriculum level, an adaptation round or a fine-tuning that never improves
  on the model it was given; a training from random weights is never stopped by it).

Steps saved are priced at each training's own processor seconds per step (``spent`` in
its fit report: Phase 1's encoder and decoder share Phase 1's, rate selection included).
What a rule costs is the kept state's validation error against the refit's kept state's
(1: the same state). Test errors would need the models scored again; validation errors
are what the rule itself sees. Each training is replayed on its own: a Phase 1 stopped
sooner would hand the trainings built on it another model, which no replay can follow,
so the savings add up the trainings as the refit ran them.

Run from the repository root, with kkl-bench installed: ``python
leaderboard/pending/issue-64/stopping_what_if.py``.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path

from kkl_bench.support.convergence import trainings

RESULTS = Path(__file__).parent / "results"
HALVINGS = (0, 1, 2, 3, 4)


def seconds_per_step(report: dict, path: str) -> float:
    """Processor seconds per optimizer step of the training at ``path`` of ``report``: its
    phase's ``spent`` (Phase 1's for its encoder and decoder; the training log's own, or
    Phase 2's, for the others)."""
    if path.startswith("phase1_log"):
        spent = report["spent"]["phase1"]
    else:
        spent = report[path.split(".")[0]].get("spent") or report["spent"].get("phase2")
    return spent["processor_seconds"] / spent["steps"] if spent and spent["steps"] else math.nan


def finished_trainings(results: Path):
    """(row, system, seed, path, record, seconds per step) of every distinct training."""
    seen = set()
    for file in sorted(results.glob("standard/**/*.json")):
        cell = json.loads(file.read_text())
        report = cell.get("fit_report") or {}
        if cell.get("status") != "ok" or "spent" not in report:
            continue
        for path, record in trainings(report):
            if "stopped" not in record:
                continue
            owner = "Phase 1" if path.startswith("phase1_log") else cell["estimator"]
            # the same curve is the same training: a variant that only uses a row's
            # networks differently online (static_hyperkkl[guard=True]) reports its row's
            key = (cell["system"], cell["seed"], path, json.dumps(record["validation_curve"]))
            if key in seen:
                continue
            seen.add(key)
            yield owner, cell["system"], cell["seed"], path, record, seconds_per_step(report, path)


def best_until(curve: list, step: float) -> float:
    """The lowest finite validation error measured at or before ``step``."""
    errors = [error for at, error in curve if at <= step and math.isfinite(error)]
    return min(errors) if errors else math.nan


def stop_after_halvings(record: dict, halvings: int) -> float | None:
    """The step where the rule ``after k halvings`` stops, or None where it does not stop
    the training sooner than the refit's rule did."""
    reductions = record.get("lr_reductions") or []
    return reductions[halvings] if len(reductions) > halvings else None


def stop_giving_up(record: dict) -> float | None:
    """The step where ``give up at the first plateau`` stops, or None where it does not."""
    reductions = record.get("lr_reductions") or []
    curve = record["validation_curve"]
    if not reductions or not curve:
        return None
    start = curve[0][1]
    improved = any(error < start for at, error in curve[1:] if at <= reductions[0])
    return None if improved else reductions[0]


def replay(rule, records) -> dict:
    """Steps and processor-hours saved by ``rule`` (a record -> stop step or None) over
    ``records``, and how the kept state's validation error compares with the refit's."""
    saved_steps = saved_seconds = 0.0
    ratios, changed = [], []
    for owner, system, seed, path, record, per_step in records:
        stop = rule(record)
        if stop is None:
            continue
        saved = record["steps"] - stop
        saved_steps += saved
        saved_seconds += saved * per_step if math.isfinite(per_step) else 0.0
        ratio = best_until(record["validation_curve"], stop) / record["best_error"]
        ratios.append(ratio)
        if ratio > 1.01:
            changed.append((ratio, f"{owner} {system} seed {seed} {path}"))
    return {
        "stopped": len(ratios),
        "steps": saved_steps,
        "core_hours": saved_seconds / 3600,
        "median_ratio": statistics.median(ratios) if ratios else math.nan,
        "worse": len(changed),
        "worst": max(changed) if changed else None,
    }


def main() -> int:
    records = list(finished_trainings(RESULTS))
    total = sum(r[4]["steps"] * r[5] for r in records if math.isfinite(r[5])) / 3600
    print(
        f"{len(records)} trainings finished under the plateau rule, "
        f"{sum(r[4]['steps'] for r in records):,.0f} steps, {total:.2f} core-hours of their "
        "optimizer steps (each at its fit's processor seconds per step)\n"
    )
    rules = {f"after {k} halvings": (lambda r, k=k: stop_after_halvings(r, k)) for k in HALVINGS}
    rules["give up at the first plateau"] = stop_giving_up
    print(
        "| rule | trainings stopped sooner | steps saved | core-hours saved | kept error / "
        "refit's (median) | worse by over 1 % | worst |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, rule in rules.items():
        r = replay(rule, records)
        worst = f"{r['worst'][0]:.3f} ({r['worst'][1]})" if r["worst"] else "-"
        print(
            f"| {name} | {r['stopped']} | {r['steps']:,.0f} | {r['core_hours']:.2f} | "
            f"{r['median_ratio']:.4f} | {r['worse']} | {worst} |"
        )
    print("\nWhere those core-hours went, per training's owner (Phase 1: every KKL row's):\n")
    print("| owner | trainings | steps | core-hours | saved after 3 halvings | after 4 |")
    print("|---|---|---|---|---|---|")
    owners = sorted({r[0] for r in records})
    rows = []
    for owner in owners:
        own = [r for r in records if r[0] == owner]
        hours = sum(r[4]["steps"] * r[5] for r in own if math.isfinite(r[5])) / 3600
        three, four = (replay(rules[f"after {k} halvings"], own)["core_hours"] for k in (3, 4))
        rows.append((hours, owner, len(own), sum(r[4]["steps"] for r in own), three, four))
    for hours, owner, count, steps, three, four in sorted(rows, reverse=True):
        print(f"| {owner} | {count} | {steps:,.0f} | {hours:.2f} | {three:.2f} | {four:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
