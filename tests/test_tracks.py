"""Tracks: declared in TOML, pinned streams of their own, the paper track unchanged."""

import json
import math
import zlib

import numpy as np
import pytest

from kkl_bench.cli import main
from kkl_bench.protocol.streams import root_seed
from kkl_bench.suite.task import Task, make_test_set
from kkl_bench.suite.tracks import (
    TRACKS_ENV,
    TrackError,
    broken_tracks,
    get_track,
    load_tracks,
    parse_track,
)
from tests.repository import BOARD_CELLS

DT = 0.05


def test_the_built_in_tracks_paper_first():
    assert list(load_tracks())[:7] == [
        "paper",
        "far-init",
        "hard",
        "mismatch",
        "more-systems",
        "noise",
        "ood-inputs",
    ]
    assert get_track("paper").task_names() == ["zero", "constant", "sinusoid", "square"]


@pytest.mark.parametrize("path", sorted(BOARD_CELLS.glob("ukf/*/*.json")), ids=lambda p: p.stem)
def test_paper_track_test_sets_match_the_committed_results(path):
    cell = json.loads(path.read_text())
    test_set = make_test_set(Task(cell["system"], cell["regime"]), cell["n_test"])
    assert test_set.stream_fingerprint == cell["stream_fingerprint"]
    assert test_set.fingerprint == cell["test_set_fingerprint"]


def test_committed_results_cover_all_sixteen_paper_cells():
    assert len(list(BOARD_CELLS.glob("ukf/*/*.json"))) == 16


def test_a_track_task_has_its_own_id_and_stream():
    task = Task("duffing", "chirp", track="ood-inputs")
    assert task.id == "ood-inputs/duffing/chirp@v1"
    assert Task("duffing", "zero").id == "duffing/zero@v1"
    expected = zlib.crc32(b"kkl-bench/v1/far-init/duffing/zero/test")
    assert root_seed("duffing", "zero", "test", "far-init") == expected
    far = make_test_set(Task("duffing", "zero", track="far-init"), 3)
    paper = make_test_set(Task("duffing", "zero"), 3)
    assert far.stream_fingerprint != paper.stream_fingerprint


def test_a_task_outside_its_track_is_a_clear_error():
    with pytest.raises(TrackError, match="track 'noise' has no task 'zero'; its tasks: constant-"):
        make_test_set(Task("duffing", "zero", track="noise"), 1)
    with pytest.raises(ValueError, match="track 'paper' is at version 1"):
        make_test_set(Task("duffing", "zero", version=2), 1)


@pytest.mark.parametrize("sigma", [0.001, 0.03, 0.1])
def test_noise_track_measures_with_its_own_noise(sigma):
    data = make_test_set(Task("vdp", f"sinusoid-sigma{sigma:g}", track="noise"), 10).data
    residual = data.y[..., 0] - data.x[..., 0]
    assert np.std(residual) == pytest.approx(sigma, rel=0.05)


def test_far_init_draws_from_three_times_the_paper_box_rossler_twice():
    x0 = make_test_set(Task("duffing", "zero", track="far-init"), 20).data.x[:, 0]
    assert np.all(np.abs(x0) <= 3.0) and np.any(np.abs(x0) > 1.0)
    rossler = make_test_set(Task("rossler", "sinusoid", track="far-init"), 20).data.x[:, 0]
    assert np.all(np.abs(rossler[:, :2]) <= 30.0) and np.any(np.abs(rossler[:, :2]) > 15.0)
    assert np.all((rossler[:, 2] >= 0.0) & (rossler[:, 2] <= 3.0)) and rossler[:, 2].max() > 1.0


def _inputs(task: str, n: int = 20) -> np.ndarray:
    return make_test_set(Task("duffing", task, track="ood-inputs"), n).data.u[..., 0]


def test_chirp_sweeps_its_frequency_band():
    # phase advance over [0, 10] s: 0.1 * 10 + 2.9 * 10^2 / 100 = 3.9 rad (about 1 zero
    # crossing); over [40, 50] s: 0.1 * 10 + 2.9 * (50^2 - 40^2) / 100 = 27.1 rad (about 8.6)
    u = _inputs("chirp", 3)
    t = DT * np.arange(u.shape[1])
    crossings = [t[1:][np.diff(np.sign(row)) != 0] for row in u]
    assert all(np.sum(c < 10.0) <= 2 and np.sum(c > 40.0) >= 7 for c in crossings)


def test_multisine_stays_within_its_amplitude_and_above_2_rad_per_s():
    u = _inputs("multisine")
    assert np.abs(u).max() <= 1.0
    spectrum = np.abs(np.fft.rfft(u, axis=1)).sum(axis=0)
    omega = 2 * np.pi * np.fft.rfftfreq(u.shape[1], DT)
    assert spectrum[omega < 1.5].sum() < 0.05 * spectrum.sum()


def test_random_steps_hold_levels_for_half_a_second_to_five():
    u = _inputs("random-steps")
    assert np.abs(u).max() <= 1.0
    for row in u:
        switches = np.flatnonzero(np.diff(row)) + 1
        holds = np.diff(switches) * DT
        assert holds.min() >= 0.5 - DT and holds.max() <= 5.0 + DT


def test_wide_sinusoid_and_ramp_leave_the_training_amplitude():
    assert np.all(np.abs(_inputs("sinusoid-2x")).max(axis=1) > 1.0)
    ramps = _inputs("ramp")
    assert np.all(np.abs(ramps[:, -1]) >= 1.0)
    assert np.allclose(np.diff(ramps, axis=1), np.diff(ramps, axis=1)[:, :1])


GOOD = """
name = "mine"
version = 2
systems = ["duffing"]

[[task]]
name = "slow"
family = "sinusoid"
omega = [0.1, 0.2]
"""


def test_a_valid_track_file_parses():
    track = parse_track(GOOD, "mine.toml")
    task = track.task("slow")
    assert (track.name, track.version, task.family, task.reference) == (
        "mine",
        2,
        "sinusoid",
        "sinusoid",
    )
    assert task.regime().omega == (0.1, 0.2) and task.regime().amplitude == (0.5, 1.0)


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            ('family = "sinusoid"', 'family = "sawtooth"'),
            "task 'slow': field 'family': unknown family 'sawtooth'; valid families: chirp",
        ),
        (
            ('["duffing"]', '["pendulum"]'),
            "field 'systems': unknown system 'pendulum'; valid systems: chua, duffing",
        ),
        (
            ('family = "sinusoid"', 'family = "chirp"'),
            "task 'slow': family 'chirp' needs parameter(s) amplitude",
        ),
        (
            ("omega = [0.1, 0.2]", "omega = [-0.1, 0.2]"),
            "task 'slow': family 'sinusoid': omega must not be negative, got [-0.1, 0.2]",
        ),
        (
            ("omega = [0.1, 0.2]", "omega = 0.1"),
            "task 'slow': family 'sinusoid': omega must be a [low, high] pair of numbers, got 0.1",
        ),
        (
            ("omega = [0.1, 0.2]", "omega = [0.1, 0.2]\nmeasurement_noise = -0.1"),
            "task 'slow': field 'measurement_noise' must be non-negative, got -0.1",
        ),
        (
            ("omega = [0.1, 0.2]", "omega = [0.1, 0.2]\nperiod = [1, 2]"),
            "task 'slow': unknown field 'period'; family 'sinusoid' takes amplitude, omega",
        ),
        (
            ("omega = [0.1, 0.2]", "omega = [0.1, 0.2]\nhorizon = 10.01"),
            "field 'horizon' must be a whole number of 0.05 s steps",
        ),
        (("version = 2", "version = 0"), "field 'version': must be a positive integer, got 0"),
        (('name = "slow"', 'name = "Slow Task"'), "field 'name': must be lower-case letters"),
        (
            ("omega = [0.1, 0.2]", 'omega = [0.1, 0.2]\nreference = "chirp"'),
            "field 'reference': 'chirp' is not a task of the paper track",
        ),
    ],
)
def test_bad_track_files_name_the_file_the_task_and_the_field(edit, message, tmp_path, monkeypatch):
    (tmp_path / "mine.toml").write_text(GOOD.replace(*edit))
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    assert "mine" not in load_tracks() and "paper" in load_tracks()  # the others load
    reason = broken_tracks()[str(tmp_path / "mine.toml")]
    assert reason.startswith(str(tmp_path / "mine.toml"))
    assert message in reason


def test_duplicate_task_ids_and_track_names_are_refused(tmp_path, monkeypatch):
    duplicated = GOOD + '\n[[task]]\nname = "slow"\nfamily = "zero"\n'
    with pytest.raises(
        TrackError, match=r"mine.toml: task 'slow': duplicate task id mine/<system>/slow"
    ):
        parse_track(duplicated, "mine.toml")
    (tmp_path / "again.toml").write_text(GOOD.replace('"mine"', '"noise"'))
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    assert load_tracks()["noise"].source == "tasks/tracks/noise.toml"
    assert (
        "track 'noise' is already declared in tasks/tracks/noise.toml"
        in (broken_tracks()[str(tmp_path / "again.toml")])
    )


def test_a_broken_track_file_is_named_and_skipped_by_list_and_run(tmp_path, monkeypatch, capsys):
    (tmp_path / "mine.toml").write_text(GOOD.replace('name = "slow"\n', ""))
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    assert main(["list"]) == 0
    listed = capsys.readouterr()
    assert f"BROKEN track file {tmp_path / 'mine.toml'} (not usable)" in listed.out
    assert "track paper@v1" in listed.out
    assert "skipped a broken track file" in listed.err
    run = ["run", "--estimator", "ekf", "--system", "duffing", "--regime", "zero"]
    assert main([*run, "--results", str(tmp_path / "results")]) == 0


def test_a_track_from_the_environment_runs_without_code(tmp_path, monkeypatch):
    (tmp_path / "mine.toml").write_text(GOOD)
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    test_set = make_test_set(Task("duffing", "slow", version=2, track="mine"), 2)
    assert test_set.task.id == "mine/duffing/slow@v2"
    assert math.isclose(np.abs(test_set.data.u).max(), 1.0, rel_tol=0.5)


@pytest.mark.parametrize("track", ["ood-inputs", "noise", "far-init"])
def test_every_track_test_set_has_a_finite_truth(track):
    for system in get_track(track).systems:
        for task in get_track(track).task_names():
            data = make_test_set(Task(system, task, track=track), 20).data
            assert np.isfinite(data.x).all() and np.isfinite(data.y).all()


def test_a_box_that_sends_the_truth_to_infinity_is_an_error(tmp_path, monkeypatch):
    (tmp_path / "wide.toml").write_text(
        'name = "wide"\nversion = 1\nsystems = ["rossler"]\n\n[[task]]\nname = "zero"\n'
        'family = "zero"\nx0_box = {rossler = {low = [40.0, 40.0, 2.0], high = [45.0, 45.0, 3.0]}}\n'
    )
    monkeypatch.setenv(TRACKS_ENV, str(tmp_path))
    with pytest.raises(
        ValueError, match=r"task wide/rossler/zero@v1: the true state of test trajectories \[0"
    ):
        make_test_set(Task("rossler", "zero", track="wide"), 3)
