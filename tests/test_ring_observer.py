"""The local ring observer: its ring declaration, equivariance, size independence and training."""

import numpy as np
import pytest
import torch
from kkl_bench.estimators.learned.ring_observer import (
    NUDGING,
    LocalRingFilter,
    RingLayout,
    RingObserver,
)

from kkl_bench import variants
from kkl_bench.kkl.sequence import inputs
from kkl_bench.measurement import MeasurementModel
from kkl_bench.protocol.system import Ring
from kkl_bench.registry import regimes, systems
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import get_profile


def network(n: int, observed_channel: bool = False, seed: int = 0) -> LocalRingFilter:
    torch.manual_seed(seed)
    model = systems.get("lorenz96-n10")().with_sites(n)
    return LocalRingFilter(RingLayout(model, 2), 0.05, 2, 8, observed_channel)


def test_lorenz96_declares_its_ring_and_resizes():
    system = systems.get("lorenz96-n10")()
    assert system.ring == Ring(sites=10, output_sites=(0, 2, 4, 6, 8))
    resized = system.with_sites(6)
    assert resized.name == "lorenz96-n6" and resized.ring.output_sites == (0, 2, 4)
    with pytest.raises(TypeError, match="duffing is not a ring system"):
        systems.get("duffing")().with_sites(6)
    with pytest.raises(ValueError, match="at most one output"):
        Ring(sites=4, output_sites=(0, 0))


def test_the_ring_observer_is_unsupported_on_a_system_without_a_ring():
    reason = RingObserver().unsupported_reason(systems.get("duffing")(), MeasurementModel())
    assert "needs a system on a ring" in reason and "duffing declares none" in reason
    assert (
        RingObserver().unsupported_reason(systems.get("lorenz96-n5")(), MeasurementModel()) is None
    )


def test_rotating_the_ring_by_two_sites_rotates_the_estimates():
    """With the input off, a rotation that maps measured sites to measured sites (two sites)
    moves every estimate with it: the model and the weights are shared by the sites."""
    net = network(10)
    with torch.no_grad():
        net.gain.weight.normal_()  # a gain that depends on the features
    rng = np.random.default_rng(0)
    y = 8 + rng.normal(size=(2, 30, 5))
    u = np.zeros((2, 30, 1))
    with torch.no_grad():
        x_hat = net(inputs(y, u, False))[0].numpy()
        rotated = net(inputs(np.roll(y, 1, axis=-1), u, False))[0].numpy()
    assert np.allclose(rotated, np.roll(x_hat, 2, axis=-1), atol=1e-4)
    assert not np.allclose(x_hat, np.roll(x_hat, 2, axis=-1), atol=1e-3)


def test_the_network_has_the_same_parameters_at_every_size_and_runs_at_another():
    small, large = network(5), network(40)
    count = [sum(p.numel() for p in net.parameters()) for net in (small, large)]
    assert count[0] == count[1]
    moved = small.on(systems.get("lorenz96-n40")())
    y, u = np.full((1, 7, 20), 8.0), np.ones((1, 7, 1))
    with torch.no_grad():
        out = moved(inputs(y, u, False))[0]
    assert out.shape == (1, 7, 40) and torch.isfinite(out).all()
    assert moved.cell is small.cell  # the same parameters
    assert small.layout.sites == 5  # the original keeps its ring


def test_the_untrained_gain_nudges_each_measured_site_towards_its_measurement():
    """One step from the box centre: with the untrained gain a measured site moves by about
    NUDGING times its innovation, an unmeasured site about not at all."""
    net = network(10)
    y = np.full((1, 1, 5), 9.0)  # the centre is 8: innovation 1 at every measured site
    with torch.no_grad():
        x_hat = net(inputs(y, np.zeros((1, 1, 1)), False))[0][0, 0].numpy()
    assert np.allclose(x_hat[::2], 8 + NUDGING, atol=0.05)
    assert np.allclose(x_hat[1::2], 8, atol=0.05)


def test_between_measurements_the_filter_runs_the_model():
    net = network(10, observed_channel=True)
    y = np.full((1, 4, 5), np.nan)
    y[:, 0] = 8.5
    u = np.zeros((1, 4, 1))
    with torch.no_grad():
        x_hat = net(inputs(y, u, True))[0][0].double()
    from kkl_bench.protocol.simulate import rk4_step

    for k in (1, 2, 3):
        step = rk4_step(net.layout.system, x_hat[k - 1], torch.zeros(()), 0.05)
        assert torch.allclose(x_hat[k], step, atol=1e-4)


def test_trained_at_five_sites_and_applied_at_ten(tmp_path):
    spec = RunSpec(
        ("ring_observer",),
        ("lorenz96-n10", "lorenz96-n5"),
        None,
        get_profile("quick"),
        cache_dir=tmp_path,
        tracks=("more-systems",),
    )
    context = make_fit_context(spec, "ring_observer", "lorenz96-n10", 0)
    fitted = variants.build("ring_observer[train_sites=5]").fit(context)
    assert fitted.fit_report()["trained_on"] == "lorenz96-n5"
    data = context.training.simulate(regimes.get("sinusoid")(), 2, stream="t", n_samples=450)
    x_hat = fitted.estimate(data.t, data.y, data.u)
    assert x_hat.shape == data.x.shape and np.isfinite(x_hat).all()
    # the same model as a fit at five sites (one cache entry)
    own = make_fit_context(spec, "ring_observer", "lorenz96-n5", 0)
    at_five = variants.build("ring_observer").fit(own)
    assert at_five.fit_report()["training_log"] == fitted.fit_report()["training_log"]


def test_bad_parameters_name_the_value():
    with pytest.raises(ValueError, match="radius=0"):
        RingObserver(radius=0)
    with pytest.raises(ValueError, match="train_sites=2"):
        RingObserver(train_sites=2)
