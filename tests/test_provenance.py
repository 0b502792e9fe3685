"""The Reproduce section's facts read from the cells: who trained a model, what was dirty."""

import pandas as pd

from kkl_bench.report.provenance import (
    NOT_RECORDED,
    dirty_cells,
    dirty_sentence,
    provenance_facts,
    runs_frame,
    training_commit_sentence,
    training_commits,
)


def cell(estimator, scored, trained=None, seed=0, status="ok", platform="Linux-a"):
    """A results row: scored at commit ``scored``, its model trained at ``trained``
    (per phase; None: no training recorded)."""
    spent = (
        None
        if trained is None
        else {f"phase{i}": {"steps": 100, "git_commit": c} for i, c in enumerate(trained)}
    )
    return {
        "estimator": estimator,
        "system": "vdp",
        "track": "paper",
        "regime": "sinusoid",
        "seed": seed,
        "status": status,
        "provenance": {"git_commit": scored, "command": "kkl-bench run", "platform": platform},
        "fit_report": {} if spent is None else {"spent": spent},
    }


def test_the_training_commits_are_read_per_phase():
    report = {"spent": {"phase1": {"git_commit": "a"}, "phase2": {"git_commit": "b-dirty"}}}
    assert training_commits(report) == {"a", "b-dirty"}
    assert training_commits({"spent": {"phase2": {"steps": 4000}}}) == set()  # older cells
    assert training_commits(None) == set()


def test_a_row_says_which_commits_trained_its_models_and_how_many_cells_each():
    results = pd.DataFrame(
        [
            cell("kkl", "c1", ["t1", "t1"]),
            cell("kkl", "c1", ["t1", "t1"], seed=1),
            cell("kkl", "c0", [], seed=2),  # trained before the commit was recorded
            cell("kkl", "c1", seed=3, status="unsupported"),  # no model: not counted
            cell("ekf", "c1"),
        ]
    )
    trained = runs_frame(results).set_index("estimator")["trained"]
    assert trained["`kkl`"] == f"`t1` (2); {NOT_RECORDED} (1)"
    assert trained["`ekf`"] == ""  # a filter trains nothing


def test_cells_made_from_uncommitted_code_are_listed():
    results = pd.DataFrame(
        [
            cell("kkl", "c1-dirty", ["t1"]),  # scored dirty
            cell("kkl", "c1", ["t1-dirty"], seed=1),  # trained dirty
            cell("kkl", "c1", ["t1"], seed=2),  # clean
        ]
    )
    dirty = dirty_cells(results)
    assert dirty.values.tolist() == [
        ["`kkl` vdp paper sinusoid seed 0", "c1-dirty", "", ""],
        ["`kkl` vdp paper sinusoid seed 1", "", "t1-dirty", ""],
    ]
    assert dirty_sentence(dirty, 3).startswith(
        "2 of the 3 cells were made by code with uncommitted changes (a commit ending "
        "`-dirty`): 1 scored and 1 trained from such a tree"
    )
    assert dirty_sentence(dirty.iloc[:0], 3) == (
        "Every one of the 3 cells was scored, and its model trained, from a committed tree."
    )


def test_a_dirty_cell_re_derived_at_a_committed_tree_says_so():
    results = pd.DataFrame(
        [cell("kkl", "c1-dirty", ["t1"]), cell("kkl", "c2-dirty", ["t1"], seed=1)]
    )
    verifications = pd.DataFrame(
        [  # the record of seed 0 as published, at a clean and then a dirty tree
            ("r1", "kkl/vdp/sinusoid-seed0.json", "c1-dirty", "v1", "within tolerance"),
            ("r2", "kkl/vdp/sinusoid-seed0.json", "c1-dirty", "v2", "identical"),
            ("r3", "kkl/vdp/sinusoid-seed0.json", "c1-dirty", "v3-dirty", "drifted"),
            # seed 1 verified when it held another record (published at c0)
            ("r2", "kkl/vdp/sinusoid-seed1.json", "c0", "v2", "identical"),
        ],
        columns=["run", "cell", "published_commit", "verified_commit", "verdict"],
    )
    dirty = dirty_cells(results, verifications)
    assert dirty["verified"].tolist() == ["identical", ""]
    assert (
        "; 1 of them re-derived since by `kkl-bench verify` at a committed tree: 1 identical, "
        in (dirty_sentence(dirty, 2))
    )
    assert "re-derived since" not in dirty_sentence(dirty_cells(results), 2)


def test_the_board_says_which_commits_trained_its_models():
    def spent(*commits):
        phases = {f"phase{i}": {"steps": 10, "git_commit": c} for i, c in enumerate(commits)}
        return {"spent": phases or {"fit": {"steps": 10}}}

    one = pd.DataFrame({"fit_report": [spent("aaa"), spent("aaa"), {}]})  # {}: a filter
    assert training_commit_sentence(one) == (
        "Every one of the 2 cells of trained models was trained at `aaa`."
    )
    mixed = pd.DataFrame({"fit_report": [spent("aaa"), spent("aaa", "bbb"), spent(), spent("aaa")]})
    assert training_commit_sentence(mixed) == (
        "The 4 cells of trained models were trained at 3 commits or sets of commits (cells "
        "each): `aaa` (2); `aaa, bbb` (1); not recorded (1)."
    )
    assert training_commit_sentence(pd.DataFrame({"fit_report": [{}]})) == ""


def test_the_platforms_are_named_with_their_cells_where_there_are_several():
    one = pd.DataFrame([cell("kkl", "c1"), cell("kkl", "c1", seed=1)]).assign(protocol="v1")
    assert provenance_facts(one)["platform"] == ["Linux-a"]
    two = pd.concat([one, pd.DataFrame([cell("kkl", "c1", seed=2, platform="Linux-b")])])
    assert provenance_facts(two.assign(protocol="v1"))["platform"] == [
        "Linux-a (2 cells)",
        "Linux-b (1 cell)",
    ]
