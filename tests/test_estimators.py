"""Every registered estimator passes the conformance kit and never trains on an
``ood-inputs`` family; the filters are accurate on easy cases."""

from unittest import mock

import numpy as np
import pytest

from kkl_bench.estimator import Estimator, NotFittedError
from kkl_bench.registry import estimators
from kkl_bench.run.scoring import score
from kkl_bench.run.spec import RunSpec, make_fit_context
from kkl_bench.suite.task import Task, get_profile, make_test_set
from kkl_bench.suite.tracks import get_track
from kkl_bench.testing import Conformance, check_estimator
from kkl_bench.training import MixtureFamily, TrainingData
from tests.budgets import few_steps

_conformance = {}
_training_inputs = {}


def conformance(name):
    """The estimator's conformance checks, fitted once (for a few optimizer steps) while its
    training inputs are recorded."""
    if name not in _conformance:
        check = Conformance(name, budget=few_steps(name))
        simulate = TrainingData.simulate
        seen = []

        def recording(self, inputs, *args, **kwargs):
            data = simulate(self, inputs, *args, **kwargs)
            seen.append((inputs, float(np.abs(data.u).max())))
            return data

        with mock.patch.object(TrainingData, "simulate", recording):
            check.fitted  # noqa: B018 (fits)
        _conformance[name], _training_inputs[name] = check, seen
    return _conformance[name]


def _components(family):
    if isinstance(family, MixtureFamily):
        return [c for member in family.families for c in _components(member)]
    return [family]


CHECK_NAMES = [name for name, _ in Conformance("ekf").checks()]


@pytest.mark.parametrize("check", CHECK_NAMES)
@pytest.mark.parametrize("name", estimators.names())
def test_conformance(name, check):
    getattr(conformance(name), check)()


@pytest.mark.parametrize("name", estimators.names())
def test_no_fit_simulates_an_ood_inputs_family(name):
    """The ``ood-inputs`` track is unseen: no fit draws its families, exceeds the training
    amplitude its wide sinusoid and ramp leave, or reaches its multisine's band."""
    conformance(name)
    track = get_track("ood-inputs")
    unseen = {
        type(track.task(task).regime()) for task in ("chirp", "multisine", "random-steps", "ramp")
    }
    lowest_ood_tone = track.task("multisine").regime().omega[0]
    for inputs, peak in _training_inputs[name]:
        for family in _components(inputs):
            assert type(family) not in unseen, f"{name} trains on {family!r}"
            assert family != track.task("sinusoid-2x").regime()
            assert max(getattr(family, "omega", (0.0, 0.0))) <= lowest_ood_tone
        assert peak <= 1.0, f"{name} trains with |u| up to {peak}"


@pytest.mark.parametrize("name", ["ekf", "ukf"])
@pytest.mark.parametrize("system", ["duffing", "vdp"])
def test_filters_track_an_easy_case(name, system):
    spec = RunSpec((name,), (system,), ("sinusoid",), get_profile("quick"))
    estimator = estimators.get(name)().fit(make_fit_context(spec, name, system, seed=0))
    fields, _ = score(estimator, make_test_set(Task(system, "sinusoid"), 5))
    # the noise floor is ~0.01-0.03 here; a filter that does not track is at 0.3 and more
    assert max(fields["rmse"]) < 0.05


def test_estimate_before_fit_is_a_clear_error():
    with pytest.raises(NotFittedError, match="ExtendedKalman is not fitted"):
        estimators.get("ekf")().estimate(np.arange(3.0), np.zeros((1, 3, 1)), np.zeros((1, 3, 1)))


class PeeksAtTheTestSet(Estimator):
    def estimate(self, t, y, u):
        return np.asarray(make_test_set(Task("duffing", "zero"), 5).data.x[: len(y), : len(t)])


class NotCausal(Estimator):
    def fit(self, context):
        self.n_x_ = context.system.n_x
        return super().fit(context)

    def estimate(self, t, y, u):
        return np.repeat(y.mean(axis=1, keepdims=True), len(t), axis=1).repeat(self.n_x_, axis=2)


def test_conformance_kit_catches_a_peeking_estimator():
    with pytest.raises(
        AssertionError, match="check_does_not_read_test_sets: TestStreamAccessError"
    ):
        check_estimator(PeeksAtTheTestSet())


def test_conformance_kit_catches_a_non_causal_estimator():
    with pytest.raises(AssertionError, match="check_causal"):
        check_estimator(NotCausal())
