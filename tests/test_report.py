"""The report model: one list of sections, rendered as Markdown and as a page."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from kkl_bench.analysis.document import HTML, MARKDOWN, Code, Figure, Section, Table, Text
from kkl_bench.estimator import Estimator
from kkl_bench.registry import estimators
from kkl_bench.report import html, markdown
from kkl_bench.report import publish as publishing


def sample() -> list[Section]:
    frame = pd.DataFrame({"estimator": ["a", "b"], "rmse": [0.125, 2.5], "system": ["vdp", "vdp"]})
    marks = pd.DataFrame({"estimator": ["", ""], "rmse": ["best", ""], "system": ["", ""]})
    shades = pd.DataFrame(
        {"estimator": [math.nan] * 2, "rmse": [1.0, 20.0], "system": [math.nan] * 2}
    )
    return [
        Section("", [Text("An *opening* with `code`.")]),
        Section(
            "Scores of `x`",
            [
                Text("Two rows."),
                Table(
                    frame,
                    {"estimator": "Estimator", "rmse": "RMSE"},
                    id="scores",
                    marks=marks,
                    shades=shades,
                    sortable=True,
                ),
                Figure("scores", "the scores"),
                Code("kkl-bench run --estimator a"),
                Text("page only", only=HTML),
                Text("README only", only=MARKDOWN),
            ],
            tab="paper",
        ),
        Section("Other", [Text("another panel")], tab="noise"),
        Section("Last words", [Text("the end")]),
    ]


def test_one_section_list_gives_both_renderings():
    text = markdown.document("Board", sample())
    assert text.startswith("# Board\n\nAn *opening* with `code`.\n\n## Scores of `x`\n\nTwo rows.")
    assert "| a           | **0.125** |\n| b           | 2.5       |" in text
    assert "![the scores](figures/scores.png)" in text
    assert "```bash\nkkl-bench run --estimator a\n```" in text
    assert "README only" in text and "page only" not in text
    page = html.document("Board", sample(), {"system": {"vdp": "Van der Pol"}})
    assert "<h2>Scores of <code>x</code></h2>" in page and "<em>opening</em>" in page
    assert '<td class="num best" style="background:#c6efce" data-value="0.125">0.125</td>' in page
    assert 'style="background:#ffc7ce"' in page  # 20 times the best: red
    assert '<tr data-system="vdp">' in page and 'id="filter-system"' in page
    assert '<img src="figures/scores.svg" alt="the scores">' in page
    assert "page only" in page and "README only" not in page
    # tabbed sections sit in panels, the first shown, between the untabbed ones
    assert page.index("An <em>opening</em>") < page.index('<nav class="tabs"')
    assert (
        page.index('<div class="panel" data-tab="paper">')
        < page.index('<div class="panel" data-tab="noise" hidden>')
        < page.index("Last words")
    )


@pytest.mark.parametrize(
    ("ratio", "colour"), [(1.0, "#c6efce"), (math.sqrt(10), "#ffeb9c"), (10.0, "#ffc7ce"),
                          (1e30, "#ffc7ce"), (math.inf, "#ffc7ce"), (math.nan, "")],
)  # fmt: skip
def test_cells_are_shaded_green_at_the_best_yellow_at_three_red_from_ten(ratio, colour):
    assert html.shade(ratio) == colour


def test_a_section_added_to_the_board_reaches_the_readme_and_the_page(monkeypatch, tmp_path):
    from kkl_bench.cli import main

    results = tmp_path / "results"
    assert main(["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero",
                 "--results", str(results)]) == 0  # fmt: skip
    added = Section("A new table", [Table(pd.DataFrame({"what": ["answer"], "value": [42]}))])
    every = publishing.sections
    monkeypatch.setattr(publishing, "sections", lambda board: [*every(board), added])
    assert main(["publish", "--results", str(results), "--out", str(tmp_path / "board")]) == 0
    readme = (tmp_path / "board" / "README.md").read_text()
    page = (tmp_path / "board" / "index.html").read_text()
    assert "## A new table" in readme and "| answer |      42 |" in readme
    assert "<h2>A new table</h2>" in page and '<td class="num" data-value="42.0">42</td>' in page


def test_no_ratio_is_drawn_against_a_diverged_ukf_and_rows_that_run_nowhere_are_left_out():
    from kkl_bench.analysis.figures import relative_ratios

    summary = pd.DataFrame(
        {
            "estimator": ["ukf", "ekf", "ukf", "ekf", "ring", "ring"],
            "system": ["duffing"] * 6,
            "regime": ["zero", "zero", "square", "square", "zero", "square"],
            "rmse_mean": [math.inf, 0.2, 0.1, 0.3, math.nan, math.nan],
            "status": ["ok"] * 4 + ["unsupported"] * 2,
            "track": ["paper"] * 6,
        }
    )
    names, cells, ratios = relative_ratios(summary)
    assert names == ["ekf", "ukf"] and cells == [("duffing", "zero"), ("duffing", "square")]
    assert math.isnan(ratios[0, 0]) and ratios[0, 1] == pytest.approx(3.0)
    assert math.isinf(ratios[1, 0]) and ratios[1, 1] == 1.0  # the UKF's own cell: "div."


class Raising(Estimator):
    """A row whose fit always raises: its cells are errors."""

    def fit(self, context):
        raise RuntimeError("this row always fails")

    def estimate(self, t, y, u):
        raise AssertionError("never fitted")


def test_the_board_says_why_a_row_is_unsupported_and_counts_only_errors_as_failed(tmp_path):
    """``ring_observer`` cannot run on Van der Pol (no ring), ``raising`` fails: the paper
    section gives the first's reason and the reading guide names only the second as
    failed, and neither among the rows that ran fewer seeds."""
    from kkl_bench.cli import main

    results = tmp_path / "results"
    estimators.register("raising")(Raising)
    try:
        arguments = ["run", "--estimator", "ekf", "ring_observer", "raising", "--system", "vdp",
                     "--regime", "zero", "--results", str(results)]  # fmt: skip
        assert main(arguments) == 1  # the failed cell
    finally:  # publishing must not need the plugin
        del estimators._loaded["raising"]
    assert main(["publish", "--results", str(results), "--out", str(tmp_path / "board")]) == 0
    readme = (tmp_path / "board" / "README.md").read_text()
    paper, _, _ = readme.partition("## Our RMSE over the paper's")
    assert (
        "- `ring_observer` on Van der Pol: needs a system on a ring (System.ring: its sites "
        "and which are measured); vdp declares none" in paper
    )
    assert "those rows show only the seeds that did not: `raising`: seed 0 failed." in paper
    assert "`ring_observer`: seed" not in readme and "ran fewer seeds" not in readme


def test_a_markdown_list_becomes_an_html_list_and_other_blocks_paragraphs():
    assert html.paragraphs("Why:\n\n- `a` on Duffing\n- b\n\n- c and\nmore") == (
        "<p>Why:</p>\n<ul><li><code>a</code> on Duffing</li><li>b</li></ul>\n<p>- c and\nmore</p>"
    )
