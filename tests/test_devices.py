"""``--device``: resolution, the training block, CPU-side random draws, and the fit record.

Most of these tests run on the CPU and assume no GPU. The move to another device is
checked on the ``meta`` device (tensors without data) and with a module that
records where it is sent. Where torch sees a CUDA GPU, the last test fits each kind
of torch training on it and on the CPU.
"""

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from kkl_bench.cli import main
from kkl_bench.cli.run import announce
from kkl_bench.run.spec import RunSpec
from kkl_bench.suite.task import get_profile
from kkl_bench.support import devices
from kkl_bench.support.devices import draw_integers, draw_normal, resolve, to_numpy, training_on
from kkl_bench.testing import Conformance


def test_auto_is_cuda_only_where_torch_sees_a_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve("auto") == "cpu" and resolve("cpu") == "cpu"
    with pytest.raises(ValueError, match="device 'cuda' was asked for, but torch sees no CUDA"):
        resolve("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve("auto") == "cuda" and resolve("cuda") == "cuda"


def test_an_unknown_device_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown device 'tpu'; valid devices: auto, cpu, cuda"):
        resolve("tpu")


class Recorder(nn.Module):
    def __init__(self):
        super().__init__()
        self.sent_to = []

    def to(self, device):
        self.sent_to.append(str(device))
        return self


def test_on_the_cpu_the_training_block_changes_nothing():
    module = Recorder()
    with training_on("cpu", module) as device:
        assert device == "cpu" and torch.zeros(1).device.type == "cpu"
    assert module.sent_to == []


def test_elsewhere_modules_and_new_tensors_go_there_and_come_back(monkeypatch):
    monkeypatch.setattr(devices, "resolve", lambda name: "meta")
    module = Recorder()
    generator = torch.Generator().manual_seed(0)
    with pytest.raises(RuntimeError, match="stop"), training_on("cuda", module) as device:
        assert device == "meta" and module.sent_to == ["meta"]
        assert torch.as_tensor(np.zeros(3)).device.type == "meta"
        # random draws stay on the CPU generator's device; noise follows the data
        assert draw_integers(5, (4,), generator).device.type == "cpu"
        like = torch.zeros(2)
        assert draw_normal((2,), generator, like).device == like.device
        raise RuntimeError("stop")
    assert module.sent_to == ["meta", "cpu"]  # back on the CPU, also after an error
    assert torch.zeros(1).device.type == "cpu"


def test_draws_equal_the_plain_torch_draws_so_cached_models_stay_valid():
    first, second = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    assert torch.equal(draw_integers(10, (6,), first), torch.randint(10, (6,), generator=second))
    assert torch.equal(
        draw_integers(9, (2, 3), first, low=4), torch.randint(4, 9, (2, 3), generator=second)
    )
    like = torch.zeros(5)
    assert torch.equal(draw_normal((5,), first, like), torch.randn((5,), generator=second))
    assert to_numpy(torch.ones(2, dtype=torch.float32)).dtype == np.float64


def test_a_fit_records_the_device_it_trained_on():
    budget = {**get_profile("quick").budget_for("gru_observer"), "rnn_steps": 4}
    spent = Conformance("gru_observer", budget=budget).fitted.fit_report()["spent"]["phase2"]
    assert spent["device"] == "cpu" and spent["steps"] == 4


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_the_cli_refuses_cuda_without_a_gpu_before_any_work(tmp_path, capsys):
    code = main(["run", "--estimator", "ekf", "--device", "cuda", "--results", str(tmp_path / "r")])
    assert code == 2
    assert "torch sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def fits_on_cpu_and_gpu(check: Conformance) -> dict:
    """``check``'s estimator fitted on ``cpu`` and on ``cuda``, by device, each from an empty
    cache (a cached model would not train again)."""
    return {
        device: check.prototype.clone().fit(
            dataclasses.replace(check.context, device=device, cache_dir=check.fresh_cache())
        )
        for device in ("cpu", "cuda")
    }


def _validation_curves(report, path=""):
    """``(path, curve)`` for every ``validation_curve`` in a fit report, in order."""
    if isinstance(report, dict):
        for key, value in report.items():
            if key == "validation_curve":
                yield path, value
            else:
                yield from _validation_curves(value, f"{path}/{key}")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize(
    "estimator", ["dynamic_hyperkkl", "gru_observer", "kalmannet", "ring_observer"]
)
def test_a_gpu_fit_sees_the_cpu_fits_samples_and_estimates_on_the_cpu(estimator):
    check = Conformance(estimator)
    fits = fits_on_cpu_and_gpu(check)
    reports = {device: fit.fit_report() for device, fit in fits.items()}
    assert {spent["device"] for spent in reports["cuda"]["spent"].values()} == {"cuda"}
    # the same initial weights and validation trajectories: the first training's error
    # before its first step is the CPU's, to float32 rounding
    (_, cpu_curve), *_ = _validation_curves(reports["cpu"])
    (_, gpu_curve), *_ = _validation_curves(reports["cuda"])
    assert gpu_curve[0][1] == pytest.approx(cpu_curve[0][1], rel=1e-5)
    # the model came back to the CPU: it estimates from CPU arrays
    assert np.isfinite(check.estimate(fits["cuda"])).all()


def test_a_run_says_where_torch_estimators_train_unless_on_the_cpu(tmp_path, capsys):
    spec = RunSpec(("ekf",), ("duffing",), None, get_profile("quick"), results_dir=tmp_path)
    said = {}
    for device in ("cpu", "cuda", None):
        announce(spec, [], 0, True, device)
        said[device] = capsys.readouterr().err
    assert "torch estimators train" not in said["cpu"]
    assert "(0 already done); torch estimators train on cuda; nothing to do" in said["cuda"]
    assert "torch estimators train on each worker's device (auto)" in said[None]
