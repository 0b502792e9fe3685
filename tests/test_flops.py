"""A network's online arithmetic counted by its layer sizes, against hand counts."""

import numpy as np
import pytest
import torch
from torch import nn

from kkl_bench.kkl.frozen import FrozenMLP
from kkl_bench.kkl.latent import LatentObserver
from kkl_bench.support import flops


def test_torch_layers_are_counted_by_their_sizes():
    network = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 2))
    assert flops.counted(lambda: network(torch.zeros(5, 3))) == 2 * 5 * (3 * 8 + 8 * 2)


# The count's own global forward hook (an LSTM's products, which torch's counter does not
# see) is registered while the compiled module runs: torch warns that global hooks fire once
# more for the compiled wrapper, which the hook ignores (it counts nn.LSTM modules only).
@pytest.mark.filterwarnings("ignore:Using `torch.compile\\(module\\)` when there are global hooks")
def test_a_compiled_function_is_counted_by_the_products_it_computes():
    """The counter cannot see into compiled code: inside a count it runs eagerly."""
    from kkl_bench.support.devices import compile_failure

    if compile_failure() is not None:
        pytest.skip(f"torch.compile fails here: {compile_failure()}")
    network = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 2))
    compiled = torch.compile(network, fullgraph=True, dynamic=False)
    compiled(torch.zeros(5, 3))  # compiled before the count
    assert flops.counted(lambda: compiled(torch.zeros(5, 3))) == 2 * 5 * (3 * 8 + 8 * 2)


def test_an_lstm_torch_does_not_see_is_counted_by_its_sizes():
    lstm = nn.LSTM(3, 16, num_layers=2, batch_first=True)
    per_sample = 2 * 4 * 16 * (3 + 16) + 2 * 4 * 16 * (16 + 16)  # the gates of both layers
    assert flops.counted(lambda: lstm(torch.zeros(2, 5, 3))) == 10 * per_sample
    assert flops.lstm_flops(lstm, 1) == per_sample


def test_a_frozen_mlp_counts_its_products_with_and_without_a_tangent():
    rng = np.random.default_rng(0)
    mlp = FrozenMLP(
        (rng.standard_normal((2, 8), dtype=np.float32), rng.standard_normal((8, 3), dtype=np.float32)),
        (np.zeros(8, np.float32), np.zeros(3, np.float32)),
    )  # fmt: skip
    x = np.zeros((5, 2))
    assert flops.counted(lambda: mlp(x)) == 2 * 5 * (2 * 8 + 8 * 3)
    # one direction for all: its first-layer product once, then value and tangent stacked
    one_direction = 2 * (5 + 1) * 2 * 8 + 2 * 10 * 8 * 3
    assert flops.counted(lambda: mlp.with_tangent(x, np.ones(2))) == one_direction
    assert flops.counted(lambda: mlp.with_tangent(x, np.ones((5, 2)))) == 2 * 10 * (16 + 24)


@pytest.mark.parametrize(("a", "recursion"), [(-np.eye(3), 0), (-np.eye(3) + 0.1, 2 * 2 * 3 * 3)])
def test_the_latent_observer_counts_its_drive_and_a_dense_recursion(a, recursion):
    observer = LatentObserver(a, np.ones((3, 1)), 0.05)
    y = np.zeros((2, 11, 1))
    drive = 2 * (2 * 20 * 1 * 3)  # Gamma0 y and Gamma1 dy over 2 x 10 steps
    assert flops.counted(lambda: observer.run(y)) == drive + 10 * recursion


def test_nothing_is_counted_outside_a_count():
    flops.add(1e9)  # no enclosing count: ignored
    assert flops.counted(lambda: None) == 0
