"""The harness records failures as cells, keeps going, and skips finished cells."""

import numpy as np
import pytest

from kkl_bench.estimator import Estimator
from kkl_bench.run.harness import RunSpec, run
from kkl_bench.run.results import load_results
from kkl_bench.suite.task import get_profile
from kkl_bench.support import provenance as provenance_module


class CentreOfBox(Estimator):
    """Always the centre of the x0 box; optionally broken in a chosen way."""

    def __init__(self, failure: str = "") -> None:
        self.failure = failure

    def fit(self, context):
        if self.failure == "fit":
            raise RuntimeError("cannot fit")
        return super().fit(context)

    def estimate(self, t, y, u):
        system = self.check_fitted().system
        if self.failure == "estimate" and u.any():
            raise RuntimeError("cannot handle inputs")
        shape = (len(y), len(t), system.n_x - (self.failure == "shape"))
        x_hat = np.broadcast_to((system.x0_low + system.x0_high)[: shape[-1]] / 2, shape).copy()
        if self.failure == "nan":
            x_hat[0, -1, 0] = np.nan
        return x_hat


def spec_for(name, tmp_path, **overrides):
    defaults = dict(
        estimators=(name,),
        systems=("duffing",),
        regimes=("zero", "sinusoid"),
        profile=get_profile("quick"),
        results_dir=tmp_path,
    )
    return RunSpec(**{**defaults, **overrides})


def variant(failure):
    return type(
        f"CentreOfBox_{failure or 'ok'}",
        (CentreOfBox,),
        {"__init__": lambda self, failure=failure: CentreOfBox.__init__(self, failure)},
    )


def test_a_raising_estimate_fails_its_cell_only(tmp_path, register_estimator):
    register_estimator("centre_estimate", variant("estimate"))
    summary = run(spec_for("centre_estimate", tmp_path))
    assert [cell.regime for cell in summary.scored] == ["zero"]
    assert [cell.regime for cell in summary.failed] == ["sinusoid"]
    assert "RuntimeError: cannot handle inputs" in summary.failed[0].error
    assert not summary.ok
    assert set(load_results(tmp_path)["status"]) == {"ok", "error"}


def test_a_failing_fit_fails_every_regime(tmp_path, register_estimator):
    register_estimator("centre_fit", variant("fit"))
    summary = run(spec_for("centre_fit", tmp_path))
    assert len(summary.failed) == 2 and all("fit failed" in cell.error for cell in summary.failed)


def test_a_wrong_shape_is_an_error_naming_the_shapes(tmp_path, register_estimator):
    register_estimator("centre_shape", variant("shape"))
    summary = run(spec_for("centre_shape", tmp_path))
    assert "estimate returned shape (5, 1001, 1); expected (5, 1001, 2)" in summary.failed[0].error


def test_nan_estimates_are_scored_as_diverged(tmp_path, register_estimator):
    register_estimator("centre_nan", variant("nan"))
    summary = run(spec_for("centre_nan", tmp_path))
    assert summary.ok and all(cell.n_diverged == 1 for cell in summary.scored)


def test_finished_cells_are_skipped_and_force_redoes_them(tmp_path, register_estimator):
    register_estimator("centre_ok", variant(""))
    first = run(spec_for("centre_ok", tmp_path))
    again = run(spec_for("centre_ok", tmp_path))
    forced = run(spec_for("centre_ok", tmp_path, force=True))
    assert (len(first.scored), len(again.scored), len(again.cached), len(forced.scored)) == (
        2,
        0,
        2,
        2,
    )
    cell = first.scored[0]
    assert cell.protocol == "v1+E1" and len(cell.test_set_fingerprint) == 16
    assert cell.provenance["versions"]["numpy"] == np.__version__
    assert cell.estimator_params == {"failure": ""}


class CountsFits(CentreOfBox):
    """The centre of the box, counting its fits (class-wide; runs are serial here)."""

    fits = 0

    def fit(self, context):
        type(self).fits += 1
        return super().fit(context)


def test_an_estimator_is_fitted_once_and_scored_on_every_track(tmp_path, register_estimator):
    register_estimator("counts_fits", CountsFits)
    spec = spec_for("counts_fits", tmp_path, tracks=("paper", "far-init", "noise"), regimes=None)
    summary = run(spec)
    assert CountsFits.fits == 1
    tasks = sorted(cell.task for cell in summary.scored)
    assert len(tasks) == 4 + 4 + 9
    assert "far-init/duffing/zero@v1" in tasks and "noise/duffing/square-sigma0.1@v1" in tasks
    assert {cell.track for cell in summary.scored} == {"paper", "far-init", "noise"}
    assert all(len(cell.settling_time_s) == 5 for cell in summary.scored)
    again = run(spec)  # a rerun finds every track's cells done
    assert (len(again.scored), len(again.cached), CountsFits.fits) == (0, 17, 1)


def test_cells_record_the_commit_checked_out_when_the_job_started(
    tmp_path, register_estimator, monkeypatch
):
    class CheckoutMovesDuringFit(CentreOfBox):
        def fit(self, context):
            monkeypatch.setattr(provenance_module, "_git_commit", lambda: "moved-on")
            return super().fit(context)

    register_estimator("checkout_moves", CheckoutMovesDuringFit)
    monkeypatch.setattr(provenance_module, "_git_commit", lambda: "at-start")
    provenance_module._static_provenance.cache_clear()
    try:
        summary = run(spec_for("checkout_moves", tmp_path))
    finally:
        provenance_module._static_provenance.cache_clear()
    assert {cell.provenance["git_commit"] for cell in summary.scored} == {"at-start"}


def test_regimes_are_task_names_of_the_selected_tracks(tmp_path):
    spec = spec_for("ekf", tmp_path, tracks=("paper", "noise"), regimes=("zero", "square-sigma0.1"))
    assert [task.id for task in spec.tasks()] == [
        "duffing/zero@v1",
        "noise/duffing/square-sigma0.1@v1",
    ]
    with pytest.raises(ValueError, match=r"unknown regime 'chirp' for track\(s\) paper, noise"):
        spec_for("ekf", tmp_path, tracks=("paper", "noise"), regimes=("chirp",))
    with pytest.raises(ValueError, match="unknown track 'noisy'; valid tracks: paper, far-init"):
        spec_for("ekf", tmp_path, tracks=("noisy",))


TRACK = """
name = "mine"
version = 1
systems = ["duffing"]

[[task]]
name = "slow"
family = "sinusoid"
measurement_noise = {sigma}
"""


def test_a_cell_of_an_edited_track_is_recomputed_with_a_warning(
    tmp_path, monkeypatch, register_estimator
):
    register_estimator("centre_ok", variant(""))
    for version, sigma in (("before", 0.01), ("after", 0.02)):
        folder = tmp_path / version
        folder.mkdir()
        (folder / "mine.toml").write_text(TRACK.format(sigma=sigma))
    spec = dict(tracks=("mine",), regimes=None, results_dir=tmp_path / "results")
    monkeypatch.setenv("KKL_BENCH_TRACKS", str(tmp_path / "before"))
    assert len(run(spec_for("centre_ok", tmp_path, **spec)).scored) == 1
    assert len(run(spec_for("centre_ok", tmp_path, **spec)).cached) == 1
    monkeypatch.setenv("KKL_BENCH_TRACKS", str(tmp_path / "after"))
    with pytest.warns(UserWarning, match="slow-seed0.json was scored on other test trajectories"):
        assert len(run(spec_for("centre_ok", tmp_path, **spec)).scored) == 1
