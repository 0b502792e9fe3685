"""`kkl-bench cost`: round-robin timing, the file it writes, and publishing with it."""

from __future__ import annotations

import pandas as pd
import pytest

from kkl_bench import cost
from kkl_bench.cli import main
from kkl_bench.leaderboard import measured_cost_table


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


def test_measured_cost_table_gives_means_largest_cell_and_ratio_to_the_ekf():
    costs = pd.DataFrame(
        {
            "estimator": ["ekf", "ekf", "fast", "fast"],
            "system": ["duffing", "vdp", "duffing", "vdp"],
            "us_per_trajectory_step": [100.0, 200.0, 2.0, 8.0],
        }
    )
    rows = [line.split("|")[1:-1] for line in measured_cost_table(costs).splitlines()[2:]]
    fast = [cell.strip() for cell in rows[1]]
    # (100 / 2 + 200 / 8) / 2 = 37.5
    assert fast == ["fast", "2", "8", "8", "37.5"]


def test_cost_command_writes_every_cell_and_refuses_other_files(tmp_path, capsys):
    out = tmp_path / "board"
    arguments = ["cost", "--estimator", "ekf", "ukf", "--system", "duffing", "--profile"]
    assert main([*arguments, "quick", "--rounds", "1", "--out", str(out)]) == 0
    costs = cost.read_costs(out / cost.COST_FILE)
    assert len(costs) == 2 * 4 and set(costs["regime"]) == {
        "zero",
        "constant",
        "sinusoid",
        "square",
    }
    assert (costs["rounds"] == 1).all() and (costs["threads"] == 1).all()
    assert (costs["us_per_trajectory_step"] > 0).all()
    assert "EKF / this" in capsys.readouterr().out
    (tmp_path / "not-costs.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"not-costs\.csv is not a `kkl-bench cost` measurement"):
        cost.read_costs(tmp_path / "not-costs.csv")
    assert cost.read_costs(tmp_path / "missing.csv") is None
