"""Choosing a model-based row's setting on validation streams (kkl_bench.fitting.tuning)."""

import warnings

import numpy as np
import pytest

from kkl_bench.fitting.tuning import choose, validation_error


def test_the_validation_error_is_the_rmse_over_the_scored_window():
    x = np.zeros((2, 20, 1))  # (batch, steps, n_x); the first ceil(0.05 * 20) = 1 step unscored
    x_hat = np.zeros_like(x)
    x_hat[:, 0] = 100.0  # the transient: not scored
    x_hat[0, 1:] = 3.0  # one trajectory off by 3 on every scored step, the other exact
    assert validation_error(x_hat, x) == pytest.approx(np.sqrt(9.0 / 2))


def test_a_candidate_that_loses_a_trajectory_scores_inf_silently_and_never_wins():
    x = np.zeros((2, 20, 1))
    blown_up = np.full_like(x, 1e200)  # squares overflow
    lost = np.full_like(x, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert validation_error(blown_up, x) == np.inf
        assert validation_error(lost, x) == np.inf
    outputs = {1.0: blown_up, 2.0: np.ones_like(x), 3.0: lost}
    best, scores = choose(
        [{"inflation": k} for k in outputs], lambda c, data: outputs[c["inflation"]], _Data(x)
    )
    assert best == {"inflation": 2.0}
    assert scores == {"inflation=1": np.inf, "inflation=2": 1.0, "inflation=3": np.inf}


class _Data:
    def __init__(self, x):
        self.x = x
