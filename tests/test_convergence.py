"""The board's convergence verdict, read from fit reports."""

from kkl_bench.support import convergence

TRAINED = {"phase2": {"steps": 10, "samples": 100}}


def report(**logs):
    return {"spent": TRAINED, **logs}


def test_a_fit_converged_when_every_training_did():
    converged = report(
        phase1_log={"decoder": {"converged": True}}, training_log={"converged": True}
    )
    assert convergence.outcomes(converged) == ["yes", "yes"]
    assert convergence.verdict([converged, converged]) == convergence.YES


def test_one_training_that_did_not_converge_decides():
    stalled = report(training_log={"levels": {"sine": {"converged": False}}, "converged": True})
    assert convergence.verdict([report(training_log={"converged": True}), stalled]) == "no"


def test_fits_without_curves_are_not_recorded_and_filters_untrained():
    assert convergence.verdict([report(training_log={"final_loss": 0.1})]) == "not recorded"
    assert convergence.verdict([report(training_log={"converged": None})]) == "not recorded"
    assert convergence.verdict([{"spent": {"phase2": {"steps": 0}}}, {}, None]) == ""


def test_the_worst_verdict_of_a_row():
    assert convergence.worst(["yes", "not recorded", "yes"]) == "not recorded"
    assert convergence.worst(["yes", "no", "not recorded"]) == "no"
    assert convergence.worst(["no", "diverged", "yes"]) == "diverged"
    assert convergence.worst(["", ""]) == ""
    assert convergence.worst(["yes", ""]) == "yes"


def test_the_verdict_reads_the_curve_not_the_stored_flag():
    """A report written under an older rule is judged by today's rule from its curve."""
    stuck = report(
        training_log={"validation_curve": [[0, 0.3], [50, 37.2], [100, 37.2]], "converged": True}
    )
    assert convergence.outcomes(stuck) == ["diverged"]
    assert convergence.verdict([stuck]) == "diverged"


def test_a_curve_still_falling_did_not_converge_and_did_not_diverge():
    falling = report(training_log={"validation_curve": [[0, 1.0], [50, 0.40], [100, 0.30]]})
    assert convergence.outcomes(falling) == ["no"]
    stored = report(training_log={"converged": False})  # no curve: divergence unknown
    assert convergence.outcomes(stored) == ["no"]


def test_curves_are_found_with_the_path_that_leads_to_them():
    report = {
        "phase1_log": {"decoder": {"validation_curve": [[0, 2.0], [10, 1.0]]}},
        "training_log": {"validation_curve": [[0, 3.0], [5, 2.5]], "final_loss": 0.1},
        "spent": {"phase1": {"steps": 10}},
    }
    assert convergence.curves(report) == [
        ("phase1_log.decoder", [[0, 2.0], [10, 1.0]]),
        ("training_log", [[0, 3.0], [5, 2.5]]),
    ]
    assert convergence.curves({"spent": {}}) == []


def test_a_fit_reached_its_cap_when_any_training_did():
    capped = {"phase1_log": {"encoder": {"stopped": "plateau"}, "decoder": {"stopped": "cap"}}}
    assert convergence.reached_cap(capped)
    stopped = {"phase1_log": {"decoder": {"stopped": "plateau"}}, "spent": {"phase1": {}}}
    assert not convergence.reached_cap(stopped)
    assert not convergence.reached_cap({"training_log": {"stopped": "diverged"}})
