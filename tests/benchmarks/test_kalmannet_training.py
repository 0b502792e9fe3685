"""What one of KalmanNet's training windows costs, its step eager and compiled.

Run with ``python -m pytest tests/benchmarks/test_kalmannet_training.py --benchmark-only``.

One window of the standard profile (32 trajectories x 100 samples, hidden size 64),
forward and backward, on each paper system, one thread: the filter's step run eagerly
(one small torch operation at a time) and compiled (:meth:`KalmanNetFilter.compile_step`).
Each records ``ms_per_window`` in its ``extra_info``; protocol 6.5 quotes the ratio.
"""

import pytest
import torch
from kkl_bench.estimators.learned.kalmannet import KalmanNetFilter

from kkl_bench.registry import systems
from kkl_bench.support.devices import compile_failure
from kkl_bench.support.executors import thread_limit

BATCH, WINDOW, HIDDEN = 32, 100, 64


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
@pytest.mark.parametrize("system", ["duffing", "vdp", "rossler", "lorenz"])
def test_kalmannet_training_window(benchmark, system, compiled):
    if compiled and compile_failure() is not None:
        pytest.skip(f"torch.compile fails here: {compile_failure()}")
    model = systems.get(system)()
    torch.manual_seed(0)
    network = KalmanNetFilter(model, 0.05, torch.zeros(model.n_x), HIDDEN, observed_channel=False)
    if compiled:
        network.compile_step()
    yu = torch.randn(BATCH, 2 * WINDOW, model.n_y + 1)
    _, state = network(yu[:, :WINDOW])  # past t = 0, as all but a sweep's first window
    state = tuple(part.detach() for part in state)

    def window():
        network.zero_grad()
        x_hat, _ = network.normalized(yu[:, WINDOW:], state)
        x_hat.pow(2).mean().backward()

    with thread_limit(1):
        window()  # compiled before timing
        benchmark.pedantic(window, rounds=5, iterations=1)
    benchmark.extra_info["ms_per_window"] = 1e3 * benchmark.stats.stats.min
