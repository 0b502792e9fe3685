"""Training throughput (protocol 6.5): the probe counts and times trainings without
running them, the table sums a fit's trainings by the steps each runs, the protocol shows
the committed measurement."""

import re

import pandas as pd
import pytest
import torch

from kkl_bench.analysis import throughput
from kkl_bench.analysis.cost import peak_gflops
from kkl_bench.cli import main
from kkl_bench.kkl.optimize import minimize, probing
from kkl_bench.suite.task import get_profile
from tests.repository import BOARD, PROTOCOL


def test_probe_counts_one_step_of_products_and_times_the_others():
    torch.manual_seed(0)
    layer = torch.nn.Linear(4, 3, bias=False)
    data = torch.randn(8, 4)
    calls = []

    def loss(step):
        calls.append(step)
        return layer(data).pow(2).mean()

    before = layer.weight.detach().clone()
    with probing(steps=3) as probe:
        training = minimize(
            loss, layer.parameters(), 1000, samples_per_step=8, validation=lambda: 1.0
        )
    # one counted step, one untimed (a compiled loss compiles there), three timed; not 1000
    assert calls == [0, 1, 2, 3, 4]
    assert not torch.equal(layer.weight, before)  # real optimizer steps
    (record,) = probe.records
    # forward (8, 4) @ (4, 3) and the weight's gradient (4, 8) @ (8, 3): 2 * 8 * 4 * 3 each
    assert record["flops_per_step"] == 2 * (2 * 8 * 4 * 3)
    assert record | {"seconds": None} == {
        "training": "training",
        "samples_per_step": 8,
        "fit_steps": 1000,
        "steps": 3,
        "seconds": None,
        "flops_per_step": 384,
    }
    assert record["seconds"] > 0
    assert training.validation == [(0, 1.0), (5, 1.0)] and len(training.losses) == 5


def test_a_fit_sums_its_trainings_by_the_steps_each_runs():
    frame = pd.DataFrame(
        {
            "estimator": ["a", "a"],
            "system": ["duffing", "duffing"],
            "training": ["duffing: phase 1", "duffing: phase 2"],
            "fit_steps": [1000, 100],
            "steps": [10, 10],
            "seconds": [0.1, 1.0],  # 10 ms and 100 ms a step: 10 s and 10 s in the fit
            "flops_per_step": [1e9, 1e9],
            "samples_per_s": [1e5, 1e3],
            "peak_gflops": [100.0, 100.0],
            "of_peak": [1.0, 0.1],
            "device": ["cpu", "cpu"],
            "git_commit": ["abc", "abc"],
        }
    )
    (fit,) = throughput.fit_throughput(frame).to_dict("records")
    assert fit["trainings"] == 2
    assert fit["optimizer_s"] == pytest.approx(20.0)
    assert fit["gflops_per_s"] == pytest.approx(1100 * 1e9 / 20.0 / 1e9)  # 55 GFLOP/s
    assert fit["of_peak"] == pytest.approx(0.55)
    assert fit["longest"] == "duffing: phase 1"  # the first of two equal times
    assert fit["longest_share"] == pytest.approx(0.5)


def test_the_table_shows_the_newest_measurement_and_the_one_before_it():
    def measured(commit, seconds):
        return {
            "estimator": "a",
            "system": "duffing",
            "training": "duffing: t",
            "fit_steps": 10,
            "steps": 10,
            "seconds": seconds,
            "flops_per_step": 1e9,
            "samples_per_s": 1.0,
            "peak_gflops": 100.0,
            "of_peak": 10 / seconds / 100,
            "git_commit": commit,
        }

    def on(device, commit, seconds):
        return {**measured(commit, seconds), "device": device}

    table = throughput.throughput_table(
        pd.DataFrame([on("cpu", "old", 1.0), on("cuda", "old", 0.1), on("cpu", "new", 0.5)])
    )
    # one row per device; a device's Before is its own earlier measurement
    assert table[["Device", "Of peak", "Before", "Commit"]].to_dict("records") == [
        {"Device": "cuda", "Of peak": "100.0%", "Before": "-", "Commit": "old"},
        {"Device": "cpu", "Of peak": "20.0%", "Before": "10.0%", "Commit": "new"},
    ]


def test_a_measurement_from_before_rows_recorded_their_device_reads_cpu(tmp_path):
    path = tmp_path / throughput.THROUGHPUT_FILE
    columns = [column for column in throughput.COLUMNS if column != "device"]
    pd.DataFrame([dict.fromkeys(columns, 1)]).to_csv(path, index=False)
    assert throughput.read_throughput(path)["device"].tolist() == ["cpu"]


def test_throughput_command_merges_its_rows_and_keeps_no_model(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("KKL_BENCH_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "board"
    args = ["throughput", "--estimator", "autonomous_kkl", "--system", "vdp", "--profile", "quick"]
    assert main([*args, "--steps", "1", "--out", str(out)]) == 0
    stored = throughput.read_throughput(out / throughput.THROUGHPUT_FILE)
    assert set(stored["estimator"]) == {"autonomous_kkl"} and len(stored) > 1
    assert (stored["flops_per_step"] > 0).all() and (stored["fit_steps"] >= 1).all()
    assert set(stored["device"]) == {"cpu"}  # the default, also where a GPU is seen
    assert "| autonomous_kkl |" in capsys.readouterr().out
    assert main([*args, "--steps", "1", "--out", str(out)]) == 0  # same commit: replaced
    assert len(throughput.read_throughput(out / throughput.THROUGHPUT_FILE)) == len(stored)
    assert not (tmp_path / "cache").exists()
    unsupported = ["throughput", "--estimator", "ring_observer", "--system", "vdp"]
    assert main([*unsupported, "--profile", "quick", "--out", str(tmp_path / "none")]) == 0
    assert len(throughput.read_throughput(tmp_path / "none" / throughput.THROUGHPUT_FILE)) == 0


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_throughput_on_cuda_without_a_gpu_is_an_error_before_any_work(tmp_path, capsys):
    args = ["throughput", "--estimator", "gru_observer", "--system", "vdp", "--profile", "quick"]
    assert main([*args, "--device", "cuda", "--out", str(tmp_path)]) == 2
    assert "torch sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / throughput.THROUGHPUT_FILE).exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_throughput_on_the_gpu_is_recorded_beside_the_gpu_s_peak(tmp_path, monkeypatch):
    monkeypatch.setenv("KKL_BENCH_CACHE", str(tmp_path / "cache"))
    args = ["throughput", "--estimator", "gru_observer", "--system", "vdp", "--profile", "quick"]
    assert main([*args, "--steps", "2", "--device", "cuda", "--out", str(tmp_path)]) == 0
    stored = throughput.read_throughput(tmp_path / throughput.THROUGHPUT_FILE)
    assert set(stored["device"]) == {"cuda"}
    assert (stored["peak_gflops"] > peak_gflops("float32", threads=1)).all()


def test_render_only_without_a_measurement_says_what_to_run(tmp_path, capsys):
    assert main(["throughput", "--render-only", "--out", str(tmp_path)]) == 1
    assert "run kkl-bench throughput without --render-only" in capsys.readouterr().out


def test_profile_sizes_reach_the_probe():
    records = throughput.probe_fit("gru_observer", "duffing", get_profile("quick"), steps=1)
    (record,) = records
    quick = get_profile("quick").budget_for("gru_observer")
    assert record["fit_steps"] == quick["rnn_steps"]


def test_protocol_shows_the_committed_measurement():
    measured = throughput.read_throughput(BOARD / throughput.THROUGHPUT_FILE)
    protocol = PROTOCOL.read_text()
    shown = re.search(r"<!-- training-throughput -->\n(.*?)\n\n", protocol, re.DOTALL)
    assert shown, "protocol 6.5 has no table after <!-- training-throughput -->"
    assert shown.group(1) == throughput.render(measured), (
        "protocol 6.5's throughput table differs from leaderboard/training-throughput.csv: "
        "paste `kkl-bench throughput --render-only`"
    )
