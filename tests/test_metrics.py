"""Metrics on hand-computed arrays."""

import math

import numpy as np
import pytest

from kkl_bench.protocol.metrics import (
    diverged,
    nrmse,
    per_state_rmse,
    rmse,
    settling_time,
    smape,
    state_scale,
    steady_state_start,
)


def test_steady_state_starts_at_ceil_five_percent():
    assert steady_state_start(1001) == 51
    assert steady_state_start(20) == 1
    assert steady_state_start(21) == 2


def pair():
    """Two trajectories of 20 steps (the first sample is transient), 2 states."""
    x = np.zeros((2, 20, 2))
    x_hat = np.zeros((2, 20, 2))
    x[0, :, 0] = 1.0  # trajectory 0: state 0 is 1, estimated 0 -> errors (1, 0)
    x[1, :, :] = 2.0
    x_hat[1, :, :] = 1.0  # trajectory 1: every error is 1
    x_hat[:, 0, :] = 100.0  # transient sample, never scored
    return x, x_hat


def test_rmse_by_hand():
    x, x_hat = pair()
    np.testing.assert_allclose(rmse(x, x_hat), [math.sqrt(0.5), 1.0])
    np.testing.assert_allclose(per_state_rmse(x, x_hat), [[1.0, 0.0], [1.0, 1.0]])


def test_smape_by_hand_with_zero_over_zero_counted_as_zero():
    x, x_hat = pair()
    # trajectory 0: state 0 term |1-0|/((1+0)/2) = 2, state 1 is 0/0 -> 0: mean 1 -> 100 %
    # trajectory 1: |2-1|/((2+1)/2) = 2/3 -> 66.67 %
    np.testing.assert_allclose(smape(x, x_hat), [100.0, 200.0 / 3.0])


def test_nrmse_divides_each_state_by_its_scale():
    x, x_hat = pair()
    np.testing.assert_allclose(nrmse(x, x_hat, np.array([2.0, 4.0])), [0.25, (0.5 + 0.25) / 2])


def test_state_scale_uses_the_steady_state_of_the_whole_set():
    x = np.zeros((2, 20, 1))
    x[0, 1:, 0] = 1.0
    x[1, 1:, 0] = -1.0
    x[:, 0, 0] = 1e6  # transient, ignored
    np.testing.assert_allclose(state_scale(x), [1.0])


def test_non_finite_estimate_diverges_its_trajectory_only():
    x, x_hat = pair()
    x_hat[1, 5, 0] = np.nan
    np.testing.assert_array_equal(diverged(x_hat), [False, True])
    assert rmse(x, x_hat)[1] == np.inf and smape(x, x_hat)[1] == np.inf
    assert np.isfinite(rmse(x, x_hat)[0])
    x_hat[0, 0, 0] = np.inf  # in the unscored transient: still a divergence
    assert np.isinf(rmse(x, x_hat)).all() and np.isinf(smape(x, x_hat)).all()
    assert np.isinf(per_state_rmse(x, x_hat)[1]).all()


def test_perfect_estimate_scores_zero():
    x = np.random.default_rng(0).normal(size=(3, 40, 2))
    assert np.all(rmse(x, x.copy()) == 0) and np.all(smape(x, x.copy()) == 0)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="must both be"):
        rmse(np.zeros((1, 10, 2)), np.zeros((1, 10, 3)))


def test_settling_time_by_hand():
    """Windows of 20 samples (1 s at 0.05 s); the threshold is 0.1 in normalized RMSE."""
    x = np.zeros((4, 100, 2))
    x_hat = np.zeros((4, 100, 2))
    x_hat[0, :30] = 1.0  # the window starting at sample 29 still holds an error of 1
    x_hat[1, -5:] = 1.0  # the last window is above the threshold: never settles
    x_hat[2, 50] = np.nan  # diverged
    x_hat[3, :, 0] = 0.1  # with scale 2 that is (0.1 / 2)^2 / 2 -> normalized RMSE 0.035
    times = settling_time(x, x_hat, np.array([2.0, 1.0]), dt=0.05)
    assert times[0] == pytest.approx(30 * 0.05)
    assert math.isinf(times[1]) and math.isinf(times[2])
    assert times[3] == 0.0


def test_settling_time_needs_one_whole_window():
    with pytest.raises(ValueError, match="shorter than one window"):
        settling_time(np.zeros((1, 5, 1)), np.zeros((1, 5, 1)), np.ones(1), dt=0.05)
