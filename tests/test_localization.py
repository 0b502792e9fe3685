"""The localized ensemble filter (LETKF): its taper, its limits and where it applies."""

import numpy as np
import pytest
from kkl_bench.estimators.filters.enkf import (
    LocalTaper,
    gaspari_cohn,
    local_transform,
    ring_taper,
    transform,
)

from kkl_bench import variants
from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol.system import Ring
from kkl_bench.registry import regimes, systems
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import get_profile


def ensembles(batch=3, members=6, n_x=8, n_y=4, seed=0):
    rng = np.random.default_rng(seed)
    forecast = rng.normal(size=(batch, members, n_x))
    predicted = forecast[..., ::2] + 0.1 * rng.normal(size=(batch, members, n_y))
    return forecast, predicted, rng.normal(size=(batch, n_y))


def test_gaspari_cohn_is_one_at_zero_continuous_and_zero_from_twice_its_half_width():
    assert gaspari_cohn(np.array([0.0]), 2.0)[0] == 1.0
    assert gaspari_cohn(np.array([4.0, 5.0]), 2.0).tolist() == [0.0, 0.0]
    below, above = gaspari_cohn(np.array([2 - 1e-9, 2 + 1e-9]), 2.0)
    assert below == pytest.approx(5 / 24) and above == pytest.approx(5 / 24)
    assert np.all(np.diff(gaspari_cohn(np.linspace(0, 5, 51), 2.0)) <= 1e-12)


def test_ring_taper_measures_distance_around_the_ring():
    taper = ring_taper(Ring(sites=8, output_sites=(0, 2, 4, 6)), 1.0)
    assert taper.shape == (8, 4)
    assert taper[7, 0] == pytest.approx(gaspari_cohn(np.array([1.0]), 1.0)[0])  # 7 -> 0: one
    assert taper[4, 0] == 0.0  # four sites away on either side


def test_the_local_analysis_with_no_taper_is_the_global_one():
    forecast, predicted, y = ensembles()
    local = local_transform(forecast, predicted, y, 0.3, LocalTaper.of(np.ones((8, 4))))
    assert np.allclose(local, transform(forecast, predicted, y, 0.3), rtol=1e-12, atol=1e-12)


def test_a_site_ignores_measurements_beyond_the_taper():
    forecast, predicted, y = ensembles()
    taper = LocalTaper.of(ring_taper(Ring(sites=8, output_sites=(0, 2, 4, 6)), 1.0))
    moved = y.copy()
    moved[:, 2] += 5.0  # the output at site 4: two sites or more from sites 0, 1, 2, 6, 7
    before = local_transform(forecast, predicted, y, 0.3, taper)
    after = local_transform(forecast, predicted, moved, 0.3, taper)
    unaffected = [0, 1, 7]
    assert np.array_equal(before[..., unaffected], after[..., unaffected])
    assert not np.allclose(before[..., 4], after[..., 4])


def test_localization_needs_a_ring_and_a_positive_half_width():
    reason = variants.build("enkf[localization=4]").unsupported_reason(
        systems.get("lorenz")(), MeasurementModel()
    )
    assert "localizes along a ring" in reason and "lorenz declares none" in reason
    with pytest.raises(ValueError, match="localization=0"):
        variants.build("enkf[localization=0]")


def test_the_letkf_tracks_lorenz96_with_few_members():
    """At 40 states with 10 members the global analysis has too few members to span the
    errors; the local one tracks."""
    spec = RunSpec(
        ("enkf",), ("lorenz96-n40",), None, get_profile("quick"), tracks=("more-systems",)
    )
    context = make_fit_context(spec, "enkf", "lorenz96-n40", 0)
    data = context.training.simulate(regimes.get("sinusoid")(), 2, stream="letkf", n_samples=300)
    scored = slice(150, None)

    def rmse(name):
        x_hat = variants.build(name).fit(context).estimate(data.t, data.y, data.u)
        return float(np.sqrt(np.mean((x_hat[:, scored] - data.x[:, scored]) ** 2)))

    local, global_ = (
        rmse("enkf[n=10,inflation=1.05,localization=3]"),
        rmse("enkf[n=10,inflation=1.05]"),
    )
    print(f"10 members at n = 40: LETKF {local:.3g}, global ETKF {global_:.3g}")
    assert local < 0.1 < global_
