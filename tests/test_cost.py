"""`kkl-bench cost`: round-robin timing, the file it writes, and publishing with it."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from kkl_bench import variants
from kkl_bench.analysis import cost
from kkl_bench.analysis.leaderboard import measured_cost_table
from kkl_bench.cli import main
from kkl_bench.report.markdown import table
from kkl_bench.run.spec import RunSpec, fit_context_for_row, make_fit_context
from kkl_bench.suite.task import get_profile


class FakeClock:
    """Stands for ``time.perf_counter``; calls advance it by their own durations."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def call(self, durations: list[float], log: list[str], name: str):
        """A call that takes ``durations[i]`` seconds the i-th time it runs."""
        runs = iter(durations)

        def run():
            log.append(name)
            self.now += next(runs)

        return run


def test_round_robin_takes_turns_keeps_the_fastest_and_stops_slow_calls(monkeypatch):
    clock, log, saved = FakeClock(), [], []
    monkeypatch.setattr(cost.time, "perf_counter", clock)
    calls = {
        "slow": clock.call([4.0, 3.0], log, "slow"),
        "fast": clock.call([1.0, 0.5, 2.0], log, "fast"),
    }
    best, counts = cost.fastest_round_robin(
        calls, rounds=3, max_seconds=5.0, after_round=lambda b, c: saved.append(dict(c))
    )
    # "slow" has spent 7 s after two timings, past max_seconds: no third one
    assert log == ["slow", "fast", "slow", "fast", "fast"]
    assert best == {"slow": 3.0, "fast": 0.5} and counts == {"slow": 2, "fast": 3}
    assert saved == [{"slow": 1, "fast": 1}, {"slow": 2, "fast": 2}, {"slow": 2, "fast": 3}]


def test_the_first_call_of_each_group_runs_untimed_before_it_is_timed(monkeypatch):
    clock, log = FakeClock(), []
    monkeypatch.setattr(cost.time, "perf_counter", clock)
    calls = {
        ("ekf", "zero"): clock.call([9.0, 1.0, 9.0, 1.0], log, "ekf zero"),
        ("ekf", "square"): clock.call([1.0, 1.0], log, "ekf square"),
        ("ukf", "zero"): clock.call([9.0, 2.0, 9.0, 2.0], log, "ukf zero"),
    }
    best, counts = cost.fastest_round_robin(calls, rounds=2, group=lambda key: key[0])
    assert log == ["ekf zero", "ekf zero", "ekf square", "ukf zero", "ukf zero"] * 2
    assert best == {("ekf", "zero"): 1.0, ("ekf", "square"): 1.0, ("ukf", "zero"): 2.0}
    assert counts == dict.fromkeys(calls, 2)


def test_a_call_slower_than_max_seconds_is_timed_once(monkeypatch):
    clock, log = FakeClock(), []
    monkeypatch.setattr(cost.time, "perf_counter", clock)
    best, counts = cost.fastest_round_robin(
        {"filter": clock.call([30.0], log, "filter")}, rounds=3, max_seconds=10.0
    )
    assert log == ["filter"] and best == {"filter": 30.0} and counts == {"filter": 1}


@pytest.mark.parametrize("bad", [{"rounds": 0}, {"threads": 0}, {"max_seconds": 0.0}])
def test_bad_timing_settings_are_refused_with_their_values(bad):
    with pytest.raises(ValueError, match="rounds and threads must be at least 1"):
        cost.fastest_round_robin({}, **bad)


def test_measured_costs_replace_the_cells_times_where_measured():
    summary = pd.DataFrame(
        {
            "estimator": ["ekf", "ekf", "ukf"],
            "system": ["duffing", "duffing", "duffing"],
            "regime": ["zero", "square", "zero"],
            "estimate_us_per_step": [300.0, 310.0, 400.0],
        }
    )
    costs = pd.DataFrame(
        {
            "estimator": ["ekf", "ekf"],
            "system": ["duffing", "duffing"],
            "regime": ["zero", "sinusoid"],
            "us_per_trajectory_step": [120.0, 125.0],
        }
    )
    replaced = cost.with_measured_costs(summary, costs)
    assert replaced["estimate_us_per_step"].tolist() == [120.0, 310.0, 400.0]
    assert summary["estimate_us_per_step"].tolist() == [300.0, 310.0, 400.0]


def test_measured_cost_table_compares_each_row_with_the_ekf_of_its_own_run():
    costs = pd.DataFrame(
        {
            "estimator": ["ekf", "ekf", "fast", "fast"],
            "system": ["duffing", "vdp", "duffing", "vdp"],
            "us_per_trajectory_step": [100.0, 200.0, 2.0, 8.0],
            # "fast" was timed in a later run, beside an EKF that took 400 and 800
            "reference_us_per_trajectory_step": [100.0, 200.0, 400.0, 800.0],
        }
    )
    rows = [line.split("|")[1:-1] for line in table(measured_cost_table(costs)).splitlines()[2:]]
    fast = [cell.strip() for cell in rows[1]]
    # (400 / 2 + 800 / 8) / 2 = 150, not the stored EKF rows' (100 / 2 + 200 / 8) / 2
    assert fast == ["fast", "2", "8", "8", "150"]


def row(estimator, regime, us, run=1, reference=100.0):
    return {
        "estimator": estimator,
        "system": "duffing",
        "track": "paper",
        "regime": regime,
        "trajectories": 20,
        "us_per_trajectory_step": us,
        "rounds": 3,
        "threads": 1,
        "seed": 0,
        "git_commit": f"commit{run}",
        "run": run,
        "reference_us_per_trajectory_step": reference,
    }


def test_a_measurement_replaces_only_the_rows_it_timed():
    stored = pd.DataFrame(
        [row("ekf", "zero", 100.0), row("ukf", "zero", 120.0), row("ukf", "square", 130.0)]
    )
    new = pd.DataFrame([row("ukf", "zero", 90.0, run=2, reference=80.0)])
    merged = cost.merge(stored, new)
    assert merged[["estimator", "regime", "us_per_trajectory_step", "run"]].values.tolist() == [
        ["ekf", "zero", 100.0, 1],
        ["ukf", "square", 130.0, 1],
        ["ukf", "zero", 90.0, 2],
    ]
    assert cost.merge(None, new).equals(new)


def test_a_file_from_before_merged_runs_reads_as_one_run_beside_its_own_ekf(tmp_path):
    legacy = pd.DataFrame([row("ekf", "zero", 100.0), row("ukf", "zero", 120.0)])
    legacy = legacy.drop(columns=["run", "reference_us_per_trajectory_step"])
    legacy.to_csv(tmp_path / "cost.csv", index=False)
    read = cost.read_costs(tmp_path / "cost.csv")
    assert read["run"].tolist() == [1, 1]
    assert read["reference_us_per_trajectory_step"].tolist() == [100.0, 100.0]


def test_cost_command_merges_its_rows_and_times_the_ekf_beside_them(tmp_path, capsys, monkeypatch):
    timed = []  # (estimator, engine) of every timed call, per run
    round_robin = cost.fastest_round_robin

    def recorded(calls, *arguments, **options):
        timed.append({(name, engine) for name, engine, _ in calls})
        return round_robin(calls, *arguments, **options)

    monkeypatch.setattr(cost, "fastest_round_robin", recorded)
    out = tmp_path / "board"
    arguments = ["cost", "--system", "duffing", "--profile", "quick", "--rounds", "1"]
    assert main([*arguments, "--estimator", "ekf", "ukf", "--out", str(out)]) == 0
    costs = cost.read_costs(out / cost.COST_FILE)
    assert len(costs) == 2 * 4 and set(costs["regime"]) == {
        "zero",
        "constant",
        "sinusoid",
        "square",
    }
    assert (costs["rounds"] == 1).all() and (costs["threads"] == 1).all()
    assert (costs["us_per_trajectory_step"] > 0).all() and (costs["run"] == 1).all()
    ekf = costs[costs["estimator"] == "ekf"]
    assert (ekf["reference_us_per_trajectory_step"] == ekf["us_per_trajectory_step"]).all()
    assert "EKF / this" in capsys.readouterr().out
    # a second run of one estimator: its rows replaced, the EKF's rows kept from run 1,
    # the EKF timed again beside it (not stored), and no EKF row of run 2
    assert main([*arguments, "--estimator", "ukf", "--out", str(out)]) == 0
    again = cost.read_costs(out / cost.COST_FILE)
    assert len(again) == 8
    assert again.groupby("estimator")["run"].unique().map(list).to_dict() == {
        "ekf": [1],
        "ukf": [2],
    }
    assert again[again["estimator"] == "ekf"].equals(ekf)
    assert again["reference_us_per_trajectory_step"].notna().all()
    assert "wrote 4 rows (run 2)" in capsys.readouterr().out
    # a row is timed on both engines; the EKF beside another row only on the one it reads
    both = {(name, engine) for name in ("ekf", "ukf") for engine in ("compiled", "reference")}
    assert timed == [both, {("ukf", "compiled"), ("ukf", "reference"), ("ekf", "compiled")}]
    assert main([*arguments, "--estimator", "ukf", "--replace", "--out", str(out)]) == 0
    assert set(cost.read_costs(out / cost.COST_FILE)["estimator"]) == {"ukf"}
    (tmp_path / "not-costs.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"not-costs\.csv is not a `kkl-bench cost` measurement"):
        cost.read_costs(tmp_path / "not-costs.csv")
    assert cost.read_costs(tmp_path / "missing.csv") is None


def test_flops_are_what_an_estimator_declares_or_its_layer_sizes_give():
    layer = torch.nn.Linear(2, 8)

    class Network:  # declares nothing: its products are counted on the test set
        def estimate(self, t, y, u):
            return layer(torch.as_tensor(y, dtype=torch.float32).expand(*y.shape[:2], 2))

    class Declared(Network):
        def flops_per_step(self):
            return 123.0

    data = SimpleNamespace(t=np.arange(5.0), y=np.zeros((3, 5, 1)), u=np.zeros((3, 5, 1)))
    assert cost.counted_flops(Network(), data) == (2 * 2 * 8, "float32")
    assert cost.counted_flops(Declared(), data) == (123.0, "float64")

    class Numpy(Network):  # computes outside torch and declares nothing: not counted
        def estimate(self, t, y, u):
            return y @ np.ones((1, 2))

    flops, precision = cost.counted_flops(Numpy(), data)
    assert math.isnan(flops) and precision == "float32"
    with pytest.raises(ValueError, match=r"float16.*float32, float64"):
        cost.peak_gflops("float16")
    with pytest.raises(ValueError, match=r"'float64' on cuda; valid: float32$"):
        cost.peak_gflops("float64", device="cuda")


def test_a_floor_adds_the_draws_and_transcendentals_a_row_declares():
    class Sampler:
        def operations_per_step(self):
            return {"normal": 30, "transcendental": 10}

    counts = cost.counted_operations(Sampler())
    assert counts == {"normal": 30.0, "uniform": 0.0, "transcendental": 10.0}
    assert cost.counted_operations(object()) == dict.fromkeys(cost.OPERATIONS, 0.0)
    unit_ns = {"normal": 2.0, "uniform": 1.0, "transcendental": 4.0}
    # 2000 flops at 1 GFLOP/s: 2 µs; 30 normals at 2 ns and 10 exps at 4 ns: 0.1 µs
    assert cost.floor_us(2000.0, 1.0, counts, unit_ns) == pytest.approx(2.1)


def test_the_operations_cost_what_this_machine_takes_for_one():
    unit_ns = cost.operation_ns(rounds=1)
    assert set(unit_ns) == set(cost.OPERATIONS)
    assert all(0 < ns < 1000 for ns in unit_ns.values())


def test_the_particle_filter_counts_a_draw_per_state_and_output_of_each_particle(tmp_path):
    spec = RunSpec(
        estimators=("particle_filter[n=50]", "enkf[inflation=1.0]"),
        systems=("lorenz",),
        tracks=("hard",),
        regimes=("outliers-sinusoid",),
        profile=get_profile("quick"),
        seeds=(0,),
        results_dir=tmp_path,
        cache_dir=tmp_path,
    )
    tasks = spec.tasks()
    pf = variants.build("particle_filter[n=50]").fit(
        fit_context_for_row(spec, "particle_filter[n=50]", "lorenz", tasks, 0)
    )
    # Lorenz, one output under outliers: 3 + 1 normals, a uniform for the component and
    # exp, the law's exp and log1p and the two-component proposal's 6 per particle
    assert pf.operations_per_step() == {"normal": 200, "uniform": 51, "transcendental": 450}
    enkf = variants.build("enkf[inflation=1.0]").fit(
        fit_context_for_row(spec, "enkf[inflation=1.0]", "lorenz", tasks, 0)
    )
    assert enkf.operations_per_step() == {"normal": 24 * 3, "uniform": 0, "transcendental": 0}


@pytest.mark.slow
def test_a_filter_is_timed_on_its_compiled_engine_with_its_reference_and_floor(tmp_path):
    out = tmp_path / "board"
    arguments = ["cost", "--system", "vdp", "--profile", "quick", "--rounds", "1"]
    assert main([*arguments, "--estimator", "ukf", "autonomous_kkl", "--out", str(out)]) == 0
    costs = cost.read_costs(out / cost.COST_FILE).set_index("estimator")
    ukf, kkl = costs.loc["ukf"], costs.loc["autonomous_kkl"]
    assert (ukf["engine"] == "compiled").all() and (ukf["precision"] == "float64").all()
    assert (ukf["reference_engine_us_per_trajectory_step"] > ukf["us_per_trajectory_step"]).all()
    assert (kkl["engine"] == "torch").all() and (kkl["precision"] == "float32").all()
    assert kkl["reference_engine_us_per_trajectory_step"].isna().all()
    for row in (ukf, kkl):  # both counted: the filter by its algorithm, the network by layers
        assert (row["flops_per_trajectory_step"] > 0).all() and (row["peak_gflops"] > 0).all()
        operations = sum(
            row[f"{kind}s_per_trajectory_step"] * row[f"{kind}_ns"] for kind in cost.OPERATIONS
        )
        floor = row["flops_per_trajectory_step"] / (row["peak_gflops"] * 1e3) + operations / 1e3
        np.testing.assert_allclose(row["floor_us_per_trajectory_step"], floor, rtol=1e-5)
        ratio = row["us_per_trajectory_step"] / floor  # the file keeps 6 digits
        np.testing.assert_allclose(row["over_floor"], ratio, rtol=1e-5)


def test_on_a_track_fitted_per_sensor_each_task_is_timed_on_its_own_fit(tmp_path, monkeypatch):
    spec = RunSpec(
        estimators=("ukf",),
        systems=("duffing",),
        tracks=("hard",),
        regimes=("outliers-sinusoid", "quantized-sinusoid", "outliers-square"),
        profile=get_profile("quick"),
        seeds=(0,),
        results_dir=tmp_path,
        cache_dir=tmp_path,
    )
    contexts = []

    class Recorder:
        def fit(self, context):
            contexts.append(context)
            return SimpleNamespace(measurement=context.measurement)

    monkeypatch.setattr(variants, "build", lambda variant: Recorder())
    fitted = cost.fitted_for_tasks(spec, "ukf", "duffing", "ukf")
    by_regime = {task.regime: model.measurement for task, model in fitted.items()}
    assert len(contexts) == 2  # one fit per sensor, as a run fits the track
    assert by_regime["outliers-sinusoid"] is by_regime["outliers-square"]
    assert by_regime["outliers-sinusoid"] != by_regime["quantized-sinusoid"]
    protocol = make_fit_context(spec, "ukf", "duffing", 0).measurement  # what it was fitted for
    assert protocol not in by_regime.values()
