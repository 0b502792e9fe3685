"""The compiled filter engines give the reference engine's estimates (filterpy's for the
EKF and the UKF, numpy's for the EnKF and the particle filter).

The two engines must agree to a relative 1e-9 on every trajectory of every quick cell of
the paper and hard tracks (the hard track's on Duffing; on the other systems, and sampled
standard cells, with ``--exhaustive``), except where no two
implementations of the filter can: a trajectory on which the reference engine itself
moves by more than that when every measurement moves by one unit in the last place (a
filter that does not contract its error there, on a chaotic system between sparse
samples or under outliers, amplifies every rounding; protocol 6.3). None is on the
paper track for the EKF and the UKF; the EnKF's and the hard track's are counted
(printed with ``-s``). A trajectory on
which both engines diverge (a non-finite estimate: the same score, ``inf``) agrees.
"""

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints
from kkl_bench.estimators.filters import kalman_kernels, kalman_large
from kkl_bench.systems.lorenz96 import lorenz96

from kkl_bench import variants
from kkl_bench.protocol.metrics import diverged
from kkl_bench.protocol.system import ReadThrough
from kkl_bench.run.spec import RunSpec, fit_context_for_row, fit_groups
from kkl_bench.suite.task import get_profile, make_test_set
from kkl_bench.testing import check_estimator

FILTERS = ("ekf", "ukf", "enkf", "particle_filter[n=100]")
"""The rows with two engines (the particle filter with fewer particles than the board's: the
engines share every operation but the count, and the test stays fast)."""
RELATIVE = 1e-9
ENGINES = ("reference", "compiled")
SYSTEMS = ("duffing", "vdp", "rossler", "lorenz")
HARD_SYSTEMS = ("duffing",)
"""The hard track's systems compared in the default run: one system takes every sensor's
code path (robust, inflated, sparse, quantized), which the kernels' generators share across
systems, while each system's own kernels are compared on the paper track. The others' hard
cells, their kernels compiled for this test alone, run with ``--exhaustive`` (from empty
caches, the hard cells of all four systems took 886 s of the test run's cores; Lorenz's
alone 340 s, 280 of them compiling, in a run at 0a5f65b)."""


def spec_for(tracks, profile="quick", tmp_path=None, systems=None, regimes=None):
    return RunSpec(
        estimators=FILTERS,
        systems=systems or SYSTEMS,
        regimes=regimes,
        tracks=tracks,
        profile=get_profile(profile),
        seeds=(0,),
        results_dir=tmp_path,
        cache_dir=tmp_path,
    )


def with_engine(name, engine):
    """The row ``name`` on ``engine``: ``particle_filter[n=500]`` -> ``particle_filter[engine=
    'compiled',n=500]``."""
    base, bracket, params = name.partition("[")
    inner = f"{params.rstrip(']')}," if bracket else ""
    return variants.canonical(f"{base}[{inner}engine={engine!r}]")


def fitted(spec, name, tasks, engine):
    """The ``engine`` of ``name`` fitted (tuned) once for ``tasks``, as the harness fits it."""
    row = with_engine(name, engine)
    estimator = variants.build(row).fit(fit_context_for_row(spec, row, tasks[0].system, tasks, 0))
    assert estimator.engine_used == engine
    return estimator


def estimates(estimator, task, n_test, nudge=False, rows=slice(None)):
    """``(batch, steps, n_x)`` estimates of ``estimator`` on ``task``'s test trajectories
    ``rows``; ``nudge`` moves every measurement up by one unit in the last place."""
    data = make_test_set(task, n_test).data
    y = np.nextafter(data.y[rows], np.inf) if nudge else data.y[rows]
    return estimator.estimate(data.t, y, data.u[rows])


def relative_difference(first, second):
    """``(batch,)`` the largest difference of two estimates over each trajectory, relative to
    the trajectory's largest estimate; infinite where they are not NaN at the same places."""
    scale = np.nanmax(np.abs(first), axis=(1, 2))
    difference = np.nanmax(np.abs(second - first), axis=(1, 2), initial=0.0) / scale
    return np.where((np.isnan(first) != np.isnan(second)).any(axis=(1, 2)), np.inf, difference)


def compare_engines(spec, name, tasks, n_test):
    """The number of trajectories compared and of those exempted as rounding-sensitive;
    fails on any other whose engines differ by more than a relative 1e-9."""
    counts = []
    for system in dict.fromkeys(task.system for task in tasks):
        for _, group in fit_groups(task for task in tasks if task.system == system):
            engines = {engine: fitted(spec, name, group, engine) for engine in ENGINES}
            counts += [compare_on(engines, name, task, n_test) for task in group]
    return tuple(int(total) for total in np.sum(counts, axis=0))


def compare_on(engines, name, task, n_test):
    """:func:`compare_engines` on one ``task``, the ``engines`` fitted for it."""
    reference = estimates(engines["reference"], task, n_test)
    compiled = estimates(engines["compiled"], task, n_test)
    differs = relative_difference(reference, compiled) > RELATIVE
    # both diverged (non-finite somewhere): the same score, inf, whatever the overflow
    # on the way (an EKF blowing up to 1e285 differs in its last digits)
    differs &= ~(diverged(reference) & diverged(compiled))
    if not differs.any():
        return reference.shape[0], 0
    (rows,) = np.nonzero(differs)  # only they need the reference run again (its cost)
    nudged = estimates(engines["reference"], task, n_test, nudge=True, rows=rows)
    exempt = relative_difference(reference[rows], nudged) > RELATIVE
    unexplained = rows[~exempt]
    assert not unexplained.size, f"{name} on {task}: trajectories {unexplained} differ"
    return reference.shape[0], int(exempt.sum())


def quick_cells():
    """``(track, system)`` of each test: every system of the paper track, the hard track's
    on :data:`HARD_SYSTEMS` (slow) and on the others (exhaustive)."""
    paper = [pytest.param("paper", system, id=f"paper-{system}") for system in SYSTEMS]
    hard = [
        pytest.param(
            "hard",
            system,
            marks=pytest.mark.slow if system in HARD_SYSTEMS else pytest.mark.exhaustive,
            id=f"hard-{system}",
        )
        for system in SYSTEMS
    ]
    return paper + hard


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize(("track", "system"), quick_cells())
def test_the_compiled_engine_equals_filterpy_on_every_quick_cell(name, track, system, tmp_path):
    spec = spec_for((track,), tmp_path=tmp_path, systems=(system,))
    compared, sensitive = compare_engines(spec, name, spec.tasks(), spec.profile.n_test)
    print(f"{name} on {track}, {system}: {sensitive} of {compared} trajectories rounding-sensitive")
    if track == "paper" and name != "enkf":  # the EnKF's members amplify rounding
        assert sensitive == 0


@pytest.mark.parametrize("n", [20, pytest.param(40, marks=pytest.mark.slow)])
@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_the_large_system_filters_equal_filterpy_on_lorenz96(name, n, tmp_path):
    """The EKF and the UKF of systems beyond the interleaved kernels' (``kalman_large``: one
    trajectory at a time, the EKF's sparse factors by their nonzeros, the UKF's sigma points
    as the columns the model sweeps, the sums and the update on BLAS)."""
    systems = (f"lorenz96-n{n}",)
    spec = spec_for(("more-systems",), tmp_path=tmp_path, systems=systems, regimes=("sinusoid",))
    compared, sensitive = compare_engines(spec, name, spec.tasks(), spec.profile.n_test)
    print(
        f"{name} on Lorenz-96, n = {n}: {sensitive} of {compared} trajectories rounding-sensitive"
    )
    assert compared > 0 and sensitive < compared


@pytest.mark.exhaustive
@pytest.mark.parametrize("name", FILTERS)
def test_the_compiled_engine_equals_filterpy_on_sampled_standard_cells(name, tmp_path):
    spec = spec_for(("paper", "hard"), profile="standard", tmp_path=tmp_path)
    tasks = spec.tasks()
    sample = [tasks[i] for i in np.random.default_rng(41).choice(len(tasks), 2, replace=False)]
    compared, sensitive = compare_engines(spec, name, sample, spec.profile.n_test)
    print(f"{name}: {sensitive} of {compared} trajectories rounding-sensitive")


@pytest.mark.parametrize(("inflation", "threshold"), [(1.0, np.inf), (1.5, 2.0)])
def test_the_large_system_ukf_stops_where_the_batch_last_kernel_does(inflation, threshold):
    """The two UKF kernels, straight on Lorenz-96 (n = 20), through what the task streams
    hold: samples without a measurement (a prediction only), measurements of 1e300 (the
    estimate runs away until the covariance has no square root: the trajectory stops), a
    prior whose square root does not exist (nothing recorded), with and without inflation
    and Huber's update."""
    model = lorenz96(20)().compiled()
    steps, n = 60, model.n_x
    y = 8.0 + np.random.default_rng(3).standard_normal((3, steps, model.n_y))
    y[1, ::3] = np.nan  # every third sample missing
    y[2, 30:] = 1e300
    u = np.repeat(np.sin(0.05 * np.arange(steps))[None], 3, axis=0)
    points = MerweScaledSigmaPoints(n, alpha=0.5, beta=2.0, kappa=0.0)
    spread = points.alpha**2 * n

    def run(kernel, P0):
        out = np.full((3, steps, n), np.nan)
        kernel(
            *model.functions, model.p, model.q, model.s, model.g, y, u, 0.01, np.full(n, 8.0),
            P0, 1e-4 * np.eye(n), 0.01 * np.eye(model.n_y), points.Wm, points.Wc, spread,
            inflation, threshold, out,
        )  # fmt: skip
        return out

    generic, large = run(kalman_kernels.ukf, np.eye(n)), run(kalman_large.ukf, np.eye(n))
    assert np.array_equal(np.isnan(generic), np.isnan(large))
    assert np.isfinite(large[:2]).all() and np.isfinite(large[2, :30]).all()
    assert np.isnan(large[2, -1]).all()  # stopped
    finite = np.isfinite(generic)
    assert np.abs(generic[finite] - large[finite]).max() <= 1e-9 * np.abs(generic[finite]).max()
    assert np.isnan(run(kalman_large.ukf, -np.eye(n))).all()
    assert np.isnan(run(kalman_kernels.ukf, -np.eye(n))).all()


@pytest.mark.parametrize(
    ("row", "system"),
    [
        ("enkf[localization=3]", "lorenz96-n10"),  # the LETKF: a transform per site
        ("enkf[n=3]", "lorenz96-n5"),  # as many outputs as members: the N x N analysis
    ],
)
def test_the_compiled_enkf_equals_the_reference_on_lorenz96(row, system, tmp_path):
    """The compiled EnKF's other analyses on a quick more-systems cell of Lorenz-96: the
    localized one (over the measurements each site weighs) and the global one where the
    members are no more than the outputs (the eigendecomposition of ``N x N``)."""
    spec = spec_for(("more-systems",), "quick", tmp_path, (system,), ("sinusoid",))
    compared, sensitive = compare_engines(spec, row, spec.tasks(), spec.profile.n_test)
    assert compared == spec.profile.n_test and sensitive == 0


@pytest.mark.parametrize("name", FILTERS)
def test_the_compiled_engines_pass_the_conformance_kit(name):
    check_estimator(with_engine(name, "compiled"), "vdp")


def test_a_system_without_a_compiled_model_runs_the_reference_engine(tmp_path):
    class Uncompiled(ReadThrough):  # a plugin's system: no compiled form
        def h(self, x):
            return self.model.h(x)

        def h_jacobian(self, x):
            return self.model.h_jacobian(x)

    spec = spec_for(("paper",), tmp_path=tmp_path)
    task = spec.tasks("vdp")[0]
    context = fit_context_for_row(spec, "ekf", "vdp", [task], seed=0)
    plugin = context.__class__(**{**context.__dict__, "system": Uncompiled(context.system)})
    estimator = variants.build("ekf").fit(plugin)
    assert estimator.engine_used == "reference"
    assert estimator.fit_report()["engine"] == "reference"


@pytest.mark.parametrize("name", ["ukf", "particle_filter"])
def test_an_unknown_engine_is_refused_with_the_valid_ones(name):
    with pytest.raises(ValueError, match=r"engine='numba'.*compiled, reference"):
        variants.build(f"{name}[engine='numba']")
