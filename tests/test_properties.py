"""Property tests of the metrics and input signals (hypothesis)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kkl_bench.protocol.metrics import nrmse, rmse, smape
from kkl_bench.registry import regimes

finite = st.floats(-1e3, 1e3, allow_nan=False)
trajectories = arrays(
    np.float64, st.tuples(st.integers(1, 3), st.integers(2, 30), st.integers(1, 3)), elements=finite
)


@given(trajectories)
def test_a_perfect_estimate_scores_zero(x):
    assert np.all(rmse(x, x.copy()) == 0) and np.all(smape(x, x.copy()) == 0)


@given(trajectories, st.data())
def test_rmse_is_symmetric_and_smape_bounded(x, data):
    x_hat = data.draw(arrays(np.float64, x.shape, elements=finite))
    np.testing.assert_allclose(rmse(x, x_hat), rmse(x_hat, x))
    assert np.all(rmse(x, x_hat) >= 0)
    values = smape(x, x_hat)
    assert np.all((values >= 0) & (values <= 200 + 1e-9))


@given(trajectories, st.data())
def test_any_non_finite_value_diverges_the_trajectory(x, data):
    x_hat = x.copy()
    index = tuple(data.draw(st.integers(0, n - 1)) for n in x.shape)
    x_hat[index] = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    assert np.isinf(rmse(x, x_hat)[index[0]]) and np.isinf(smape(x, x_hat)[index[0]])
    assert np.isinf(nrmse(x, x_hat, np.ones(x.shape[-1]))[index[0]])


@settings(max_examples=50)
@given(
    st.sampled_from(["zero", "constant", "sinusoid", "square"]),
    arrays(
        np.float64,
        st.tuples(st.integers(1, 5), st.just(3)),
        elements=st.floats(0, 1, exclude_max=True),
    ),
    arrays(np.float64, st.integers(1, 50), elements=st.floats(0, 100)),
)
def test_signals_stay_within_their_amplitude(name, r, t):
    regime = regimes.get(name)()
    params = regime.params_from_uniform(r)
    u = regime.signal(t, params)
    assert u.shape == (len(r), len(t)) and np.all(np.isfinite(u))
    amplitude = params[:, :1] if name in ("sinusoid", "square") else np.ones((len(r), 1))
    assert np.all(np.abs(u) <= np.abs(amplitude) + 1e-12) and np.all(np.abs(u) <= 1.0)
