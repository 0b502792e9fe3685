"""`kkl-bench publish`: reproducible files, numbers that match the stored records, a page
that works in a real browser."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from kkl_bench.analysis import figures
from kkl_bench.cli import main
from kkl_bench.estimator import Estimator
from kkl_bench.registry import estimators
from kkl_bench.run.harness import RunSpec, run
from kkl_bench.suite.task import get_profile
from tests.repository import BOARD

pytest.importorskip("matplotlib")


class OffsetCentre(Estimator):
    """The x0 box centre plus an offset that depends on the training seed (a fake learned row)."""

    def __init__(self, scale: float = 0.1) -> None:
        self.scale = scale

    def estimate(self, t, y, u):
        context = self.check_fitted()
        centre = (context.x0_low + context.x0_high) / 2 + self.scale * (1 + context.seed)
        return np.broadcast_to(centre, (len(y), len(t), context.system.n_x)).copy()


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Quick-profile cells of ekf (run once) and a seeded fake row and its variant, 2 seeds,
    on the paper track and the far-init track."""
    directory = tmp_path_factory.mktemp("results")
    estimators.register("offset_centre")(OffsetCentre)
    try:
        spec = RunSpec(
            ("ekf", "offset_centre", "offset_centre[scale=0.3]"),
            ("duffing", "vdp"),
            ("zero", "square"),
            get_profile("quick"),
            seeds=(0, 1),
            results_dir=directory,
            tracks=("paper", "far-init"),
        )
        assert run(spec).ok
    finally:  # publishing must not need the plugin
        del estimators._loaded["offset_centre"]
    return directory


@pytest.fixture(scope="module")
def published(results, tmp_path_factory):
    out = tmp_path_factory.mktemp("leaderboard")
    assert (
        main(["publish", "--results", str(results), "--profile", "quick", "--out", str(out)]) == 0
    )
    return out


def test_publishing_twice_gives_byte_identical_files(results, published, tmp_path):
    assert (
        main(["publish", "--results", str(results), "--profile", "quick", "--out", str(tmp_path)])
        == 0
    )
    first = {p.relative_to(published): p.read_bytes() for p in published.rglob("*") if p.is_file()}
    second = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert set(first) == set(second) and len(first) > 10
    assert [name for name in first if first[name] != second[name]] == []
    expected = {"README.md", "index.html", "quick.tex", "quick.csv", "quick-far-init.csv"}
    assert expected | {"figures/relative-rmse-far-init.svg"} <= {str(p) for p in first}


def test_publishing_again_draws_only_the_figures_whose_inputs_or_files_changed(
    results, published, tmp_path, monkeypatch
):
    """The same results into the same board: every figure is kept, but one edited by hand,
    which is drawn again, byte for byte as it was (``tmp_path`` and ``published`` lie side
    by side, so the copy names the same results folder)."""
    shutil.copytree(published, tmp_path, dirs_exist_ok=True)
    drawn, save = [], figures.save
    monkeypatch.setattr(figures, "save", lambda figure, path: drawn.append(path.name) or save(figure, path))  # fmt: skip
    arguments = ["publish", "--results", str(results), "--profile", "quick", "--out", str(tmp_path)]
    assert main(arguments) == 0 and drawn == []
    (tmp_path / "figures" / "relative-rmse.png").write_bytes(b"edited by hand")
    assert main(arguments) == 0 and drawn == ["relative-rmse"]
    first = {p.relative_to(published): p.read_bytes() for p in published.rglob("*") if p.is_file()}
    again = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert first == again


def recorded(results: Path) -> dict[tuple[str, str, str, str], list[dict]]:
    """The JSON records by (track, estimator, system, regime), one per seed, read straight
    from the files."""
    cells: dict[tuple[str, str, str, str], list[dict]] = {}
    paths = [*results.glob("quick/*/*/*.json"), *results.glob("quick/*/*/*/*.json")]
    for path in sorted(paths):
        record = json.loads(path.read_text())
        key = (record["track"], record["estimator"], record["system"], record["regime"])
        cells.setdefault(key, []).append(record)
    return cells


def sections(text: str) -> dict[str, str]:
    """The README's text per track: the paper track's before ``## Tracks``, then each
    ``### Track `name``` section."""
    paper, _, rest = text.partition("## Tracks")
    found = re.findall(r"### Track `([^`]+)`\n(.*?)(?=### Track |## Provenance)", rest, flags=re.S)
    return {"paper": paper, **dict(found)}


def test_publishing_needs_no_plugin_installed_and_names_the_seed_free_rows(published):
    # `offset_centre` was unregistered after its run; `ekf` is installed and seed-free
    text = (published / "README.md").read_text()
    assert "do not depend on the seed\n(`ekf`) were run once" in text
    assert "| offset_centre[scale=0.3] | 2 " in text


def test_every_number_in_the_markdown_tables_is_the_stored_result(results, published):
    text = (published / "README.md").read_text()
    titles = {"Duffing": "duffing", "Van der Pol": "vdp", "Rossler": "rossler", "Lorenz": "lorenz"}
    regimes = {"Zero": "zero", "Const": "constant", "Sin": "sinusoid", "Sqr": "square"}
    stored = recorded(results)
    checked = settling_checked = 0
    assert set(sections(text)) == {"paper", "far-init"}
    for track, section in sections(text).items():
        for table in re.findall(r"(\| Estimator +\| Seeds .*?)\n\n", section, flags=re.S):
            lines = table.splitlines()
            header = [cell.strip() for cell in lines[0].strip("|").split("|")]
            for line in lines[2:]:
                cells = [cell.strip() for cell in line.strip("|").split("|")]
                if cells[0].startswith("paper:"):
                    continue
                key = None
                first = header.index("Converged") + 1 if "Converged" in header else 2
                for title, cell in zip(header[first:], cells[first:], strict=True):
                    if title == "settle (s)":  # the median settling time of the cell before
                        times = [t for record in stored[key] for t in record["settling_time_s"]]
                        check_settling_cell(cell, times)
                        settling_checked += 1
                        continue
                    system_title, _, regime_title = title.rpartition(" ")
                    key = (track, cells[0], titles[system_title], regimes[regime_title])
                    checked += check_rmse_cell(cell, cells[1], stored.get(key))
    assert checked == 2 * 3 * 4  # two tracks, three rows, two systems x two regimes
    assert settling_checked == 3 * 4 and "settle (s)" not in sections(text)["paper"]


def check_settling_cell(cell: str, times: list[float]) -> None:
    """A settle (s) cell: the median settling time, or ``never (k/n)`` if it is infinite."""
    times = [float(t) for t in times]  # JSON stores inf as "inf"
    never = int(np.isinf(times).sum())
    if np.isinf(np.median(times)):
        assert cell == f"never ({never}/{len(times)})"
    else:
        assert float(cell.split()[0]) == pytest.approx(np.median(times), abs=0.05)
        assert cell.endswith(f"({never}/{len(times)} never)") == (never > 0)


def check_rmse_cell(cell: str, seeds: str, records: list[dict] | None) -> int:
    """Check one table cell against its records; 1 if it was checked, 0 for a ``-``."""
    if cell == "-":  # columns of the paper's rows only
        assert records is None
        return 0
    means = [np.mean(record["rmse"]) for record in records]
    assert seeds == str(len(means))
    number = re.match(r"[*]*([0-9.e+-]+)[*]*(?: ± ([0-9.e+-]+))? \(", cell)
    assert number, cell
    assert float(number[1]) == pytest.approx(np.mean(means), rel=5e-3)
    if len(means) > 1:
        assert float(number[2]) == pytest.approx(np.std(means, ddof=1), rel=5e-2, abs=1e-12)
    else:
        assert number[2] is None
    return 1


STUDY = ("scaling.csv", "figures/scaling.svg", "figures/scaling-curves.svg")


@pytest.fixture
def page(results, tmp_path):
    """A board published beside the committed scaling study (as `kkl-bench scaling` leaves
    it in the folder), if this checkout has one."""
    out = tmp_path / "board"
    for name in STUDY:
        if (BOARD / name).exists():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(BOARD / name, out / name)
    arguments = ["publish", "--results", str(results), "--profile", "quick", "--out", str(out)]
    assert main(arguments) == 0
    return out


def test_the_page_leads_with_the_board_switches_tracks_sorts_and_filters_in_a_browser(
    page, tmp_path
):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed")
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if browser is None or driver_path is None:
        pytest.skip("no browser: install Debian's chromium and chromium-driver packages")
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--window-size=1400,1000",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(
        service=webdriver.ChromeService(executable_path=driver_path), options=options
    )
    try:
        driver.get((page / "index.html").as_uri())
        errors = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
        assert errors == []
        text = driver.find_element(By.TAG_NAME, "body").text
        assert "**" not in text and "`" not in text  # the Markdown is rendered

        def visible_tables():
            return [t for t in driver.find_elements(By.TAG_NAME, "table") if t.is_displayed()]

        # the paper track's panel leads with its table in the paper's layout, coloured
        first = visible_tables()[0]
        assert first.get_attribute("id") == "board-paper-0"
        assert first.find_element(By.CSS_SELECTOR, "thead th").text == "Estimator"
        headers = [th.text for th in first.find_elements(By.CSS_SELECTOR, "thead th")]
        assert headers[1] == "Seeds" and "Converged" not in headers  # no row here trains
        assert "background" in first.find_element(
            By.CSS_SELECTOR, "tbody td:nth-child(3)"
        ).get_attribute("style")
        assert not driver.find_element(By.ID, "board-far-init-0").is_displayed()
        driver.find_element(By.TAG_NAME, "summary").click()  # the folded reading guide
        assert "Bold" in [e.text for e in driver.find_elements(By.CSS_SELECTOR, "p strong")]

        def column(table_id, name):
            table = driver.find_element(By.ID, table_id)
            headers = [th.text for th in table.find_elements(By.CSS_SELECTOR, "thead th")]
            index = headers.index(name)
            return [
                row.find_elements(By.TAG_NAME, "td")[index].get_attribute("data-value")
                or row.find_elements(By.TAG_NAME, "td")[index].text
                for row in table.find_elements(By.CSS_SELECTOR, "tbody tr")
                if row.is_displayed()
            ]

        # the long table is folded under the paper-layout tables until asked for
        long_table = driver.find_element(By.ID, "results")
        assert not long_table.is_displayed()
        long_table.find_element(By.XPATH, "ancestor::details/summary").click()
        assert long_table.is_displayed()
        before = column("results", "RMSE")
        driver.find_element(By.XPATH, "//table[@id='results']//th[text()='RMSE']").click()
        ascending = [float(v) for v in column("results", "RMSE")]
        assert ascending == sorted(ascending) and ascending != [float(v) for v in before]
        driver.find_element(By.XPATH, "//table[@id='results']//th[text()='RMSE']").click()
        assert [float(v) for v in column("results", "RMSE")] == sorted(ascending, reverse=True)

        everything = len(column("results", "System"))
        Select(driver.find_element(By.ID, "filter-system")).select_by_value("vdp")
        assert set(column("results", "System")) == {"vdp"}
        assert len(column("results", "System")) == everything // 2
        Select(driver.find_element(By.ID, "filter-regime")).select_by_value("square")
        assert set(column("results", "Regime")) == {"square"}
        assert len(column("results", "Regime")) == everything // 4
        Select(driver.find_element(By.ID, "filter-system")).select_by_value("")
        Select(driver.find_element(By.ID, "filter-regime")).select_by_value("")

        # another track: its panel replaces the paper's, and its long table sorts
        driver.find_element(By.CSS_SELECTOR, 'button.tab[data-tab="far-init"]').click()
        assert visible_tables()[0].get_attribute("id") == "board-far-init-0"
        assert not driver.find_element(By.ID, "board-paper-0").is_displayed()
        panel = driver.find_element(By.CSS_SELECTOR, 'div.panel[data-tab="far-init"]')
        # in order: the one-line answer, the paper-layout table, the long table folded
        order = [
            "answer"
            if e.tag_name == "p" and e.text.startswith("In one line.")
            else e.get_attribute("id") or e.tag_name
            for e in panel.find_elements(By.CSS_SELECTOR, "p, table, details")
        ]
        assert order.index("answer") < order.index("board-far-init-0") < order.index("details")
        assert order.index("details") + 1 == order.index("track-far-init")
        panel.find_element(By.CSS_SELECTOR, "details.table summary").click()
        driver.find_element(By.XPATH, "//table[@id='track-far-init']//th[text()='RMSE']").click()
        sorted_rmse = [float(v) for v in column("track-far-init", "RMSE")]
        assert sorted_rmse == sorted(sorted_rmse) and len(sorted_rmse) > 1
        # the panel answers first, and its heat map spans the page (legible at 1400 px)
        assert panel.find_element(By.TAG_NAME, "p").text.startswith("In one line.")
        heat_map = panel.find_element(By.CSS_SELECTOR, ".wide img")
        assert heat_map.get_attribute("src").endswith("figures/relative-rmse-far-init.svg")
        assert heat_map.size["width"] >= 1000
        driver.save_screenshot(str(tmp_path / "leaderboard-page.png"))
        if (page / "scaling.csv").exists():  # the scaling study is a panel with its figures
            driver.find_element(By.CSS_SELECTOR, 'button.tab[data-tab="scaling"]').click()
            study = driver.find_element(By.CSS_SELECTOR, 'div.panel[data-tab="scaling"]')
            assert study.find_element(By.TAG_NAME, "h3").text.startswith("Scaling study")
            assert "autonomous_kkl" in study.find_element(By.TAG_NAME, "table").text
            figure = study.find_element(By.CSS_SELECTOR, ".wide img")
            assert figure.get_attribute("src").endswith("figures/scaling.svg")
            assert figure.size["width"] >= 1000
            # a table wider than the page says so
            cues = [box for box in study.find_elements(By.CSS_SELECTOR, "div.scroll")
                    if box.get_property("scrollWidth") > box.get_property("clientWidth")]  # fmt: skip
            assert all("overflows" in box.get_attribute("class") for box in cues)
            driver.save_screenshot(str(tmp_path / "scaling-panel.png"))
        assert [e for e in driver.get_log("browser") if e["level"] == "SEVERE"] == []
        assert (tmp_path / "leaderboard-page.png").stat().st_size > 10_000
    finally:
        driver.quit()


def test_a_cost_measurement_replaces_the_scoring_runs_times(results, tmp_path):
    """With a ``kkl-bench cost`` file in the folder, the cost table shows its times."""
    from kkl_bench.analysis.cost import COLUMNS, COST_FILE

    measured = {
        "estimator": "ekf",
        "system": "duffing",
        "track": "paper",
        "trajectories": 20,
        "rounds": 3,
        "threads": 1,
        "seed": 0,
        "git_commit": "abc1234",
        "run": 1,
        "reference_us_per_trajectory_step": 120.0,
    }
    rows = [
        {**measured, "regime": regime, "us_per_trajectory_step": value}
        for regime, value in (("zero", 111.0), ("square", 333.0))
    ]
    pd.DataFrame(rows, columns=COLUMNS).to_csv(tmp_path / COST_FILE, index=False)
    arguments = ["publish", "--results", str(results), "--profile", "quick"]
    assert main([*arguments, "--out", str(tmp_path)]) == 0
    readme = (tmp_path / "README.md").read_text()
    assert "Estimation times come from one `kkl-bench cost` run" in readme
    assert "commit abc1234" in readme
    ekf_duffing = next(
        line for line in readme.splitlines() if re.match(r"\| ekf +\| duffing ", line)
    )
    assert " 222 " in ekf_duffing  # the mean of the two measured regimes
    page = (tmp_path / "index.html").read_text()
    assert "Estimation times come from one <code>kkl-bench cost</code> run" in page
    assert '(<a href="cost.csv"><code>cost.csv</code></a>, commit abc1234)' in page


class FailsOnSeedOne(OffsetCentre):
    """OffsetCentre, except that its fit raises for seed 1."""

    def fit(self, context):
        if context.seed == 1:
            raise RuntimeError("no luck with seed 1")
        return super().fit(context)


def test_a_board_says_what_its_runs_were_and_what_it_is(tmp_path, capsys):
    """A 1-seed, 2-track run read back: the Reproduce table states exactly that run, a smoke
    profile says so and compares nothing with the paper, a failed seed is named."""
    results, out = tmp_path / "results", tmp_path / "board"
    run_ekf = ["run", "--estimator", "ekf", "--system", "vdp", "--regime", "zero"]
    run_ekf += ["--track", "paper", "far-init", "--results", str(results)]
    assert main(run_ekf) == 0
    estimators.register("fails_on_seed_one")(FailsOnSeedOne)
    try:
        run_failing = ["run", "--estimator", "fails_on_seed_one", "--system", "vdp"]
        run_failing += ["--regime", "zero", "--seed", "0", "1", "--results", str(results)]
        assert main(run_failing) == 1
    finally:
        del estimators._loaded["fails_on_seed_one"]
    assert main(["publish", "--results", str(results), "--out", str(out)]) == 0
    readme = (out / "README.md").read_text()
    reproduce = readme.split("## Reproduce")[1]
    runs = reproduce.split("| Row ")[1].split("\n\n")[0]  # the runs table, not the dirty one
    rows = {line.split("|")[1].strip(): line for line in runs.splitlines() if "| `" in line}
    assert set(rows) == {"`ekf`", "`fails_on_seed_one`"}
    ekf = [cell.strip() for cell in rows["`ekf`"].split("|")[1:-1]]
    assert ekf[1:3] == ["0 on paper, far-init", "2"]
    assert ekf[4] == ""  # a filter trains nothing
    assert (
        ekf[5]
        == "`kkl-bench run --estimator ekf --system vdp --regime zero --track paper far-init "
        "--results '<...>/results'`"  # a folder outside the one the run started in
    )
    failing = [cell.strip() for cell in rows["`fails_on_seed_one`"].split("|")[1:-1]]
    assert failing[1] == "0, 1 on paper"
    assert "[`results/`](results/)" not in readme and "[`../results/`](../results/)" in readme
    assert "`fails_on_seed_one`: seed 1 failed" in readme
    assert readme.split("\n")[2].startswith("**A smoke test.** Profile `quick`")
    for section in ("## Our RMSE over the paper's", "## The paper's findings, re-tested"):
        body = readme.split(section)[1].split("\n## ")[0]
        assert "Left out: profile `quick` is a smoke test" in body
        assert "| Method" not in body and "Claim" not in body


def test_publish_owns_its_folder_and_removes_what_it_no_longer_writes(results, tmp_path):
    out = tmp_path / "board"
    arguments = ["publish", "--results", str(results), "--profile", "quick", "--out", str(out)]
    assert main(arguments) == 0
    manifest = json.loads((out / "publication.json").read_text())
    assert manifest["profile"] == "quick" and manifest["results"] == os.path.relpath(results, out)
    assert "figures/relative-rmse-far-init.svg" in manifest["files"]
    (out / "figures" / "mine.png").write_bytes(b"not published")  # not publish's: kept
    # the same board again from fewer results: the far-init files go, nothing else
    paper_only = tmp_path / "paper-only"
    shutil.copytree(
        results / "quick", paper_only / "quick", ignore=shutil.ignore_patterns("far-init")
    )
    moved = ["publish", "--results", str(paper_only), "--profile", "quick", "--out", str(out)]
    assert main(moved) == 2  # another results folder: refused without --force
    assert main([*moved, "--force"]) == 0
    assert not (out / "figures" / "relative-rmse-far-init.svg").exists()
    assert not (out / "quick-far-init.csv").exists()
    assert (out / "figures" / "mine.png").exists() and (out / "quick.csv").exists()
    # a folder with a board that no publication recorded is refused too
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "README.md").write_text("# someone's notes\n")
    assert main([*arguments[:-1], str(stranger)]) == 2
    assert (stranger / "README.md").read_text() == "# someone's notes\n"
