"""Sections (:mod:`kkl_bench.analysis.document`) as one self-contained page (no server, no network).

Sections with a ``tab`` go into one panel per tab, chosen by buttons; the others
stand above and below the panels. Tables with shades colour each cell by its
distance from the best possible; sortable tables sort by any column, and their
rows (and figures with ``data-system`` / ``data-regime``) follow the page's
system and regime filters.
"""

from __future__ import annotations

import html
import itertools
import math
import numbers
import re

import pandas as pd

from kkl_bench.analysis.document import HTML, Code, Figure, Section, Table, Text, shown


def inline(markdown: str) -> str:
    """Inline Markdown (`code`, **bold**, *italics*, [links](to)) of already escaped text
    as HTML."""
    text = re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", r'<a href="\2">\1</a>', markdown)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    text = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", text)
    return re.sub(r"\*([^*]+)\*", r"<em>\1</em>", text)


def paragraphs(markdown: str) -> str:
    """Markdown text blocks (separated by blank lines) as HTML: a block whose every line
    starts with ``- `` as a list, any other as a paragraph."""
    return "\n".join(_block(part) for part in markdown.split("\n\n") if part.strip())


def _block(part: str) -> str:
    lines = part.strip().splitlines()
    if all(line.startswith("- ") for line in lines):
        items = "".join(f"<li>{inline(html.escape(line[2:]))}</li>" for line in lines)
        return f"<ul>{items}</ul>"
    return f"<p>{inline(html.escape(part))}</p>"


def shade(ratio: float) -> str:
    """A background colour for a cell ``ratio`` times the best possible: green at 1,
    yellow at about 3, red from 10 on (log scale); diverged cells are red."""
    if not isinstance(ratio, float | int) or math.isnan(ratio):
        return ""
    position = 1.0 if math.isinf(ratio) else min(max(math.log10(max(ratio, 1.0)), 0.0), 1.0)
    stops = [(0.0, (198, 239, 206)), (0.5, (255, 235, 156)), (1.0, (255, 199, 206))]
    for (x0, c0), (x1, c1) in itertools.pairwise(stops):
        if position <= x1:
            weight = (position - x0) / (x1 - x0)
            rgb = [round(a + weight * (b - a)) for a, b in zip(c0, c1, strict=True)]
            return "#" + "".join(f"{value:02x}" for value in rgb)
    return "#ffc7ce"


def _number_text(value, block: Table) -> str:
    if pd.isna(value):  # NaN, or a count column's missing value (pd.NA)
        return ""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return html.escape(str(value))
    if isinstance(value, numbers.Integral):
        return format(value, block.intfmt)
    return format(value, block.floatfmt)


def _sort_value(value) -> str:
    """A ``data-value`` for sorting numbers: as they are, missing or infinite as +inf."""
    if pd.isna(value) or not math.isfinite(value):
        return "Infinity"
    return repr(float(value))


def table(block: Table) -> str:
    frame, headers = block.frame, block.headers
    numeric = {
        column: pd.api.types.is_numeric_dtype(frame[column])
        and not pd.api.types.is_bool_dtype(frame[column])
        for column in headers
    }
    head = "".join(
        f'<th class="{"num" if numeric[column] else "text"}">{inline(html.escape(title))}</th>'
        for column, title in headers.items()
    )
    rows = []
    for index, row in frame.iterrows():
        attributes = "".join(
            f' data-{key}="{html.escape(str(row[key]))}"'
            for key in ("system", "regime")
            if block.sortable and key in frame
        )
        cells = []
        for column in headers:
            value = row[column]
            classes = ["num" if numeric[column] else "text"]
            mark = block.marks.at[index, column] if block.marks is not None else ""
            if mark:
                classes.append(mark)
            style = shade(block.shades.at[index, column]) if block.shades is not None else ""
            extra = f' style="background:{style}"' if style else ""
            if numeric[column]:
                extra += f' data-value="{_sort_value(value)}"'
                text = _number_text(value, block)
            else:
                text = inline(html.escape(str(value))).replace("&lt;br&gt;", "<br>")
            cells.append(f'<td class="{" ".join(classes)}"{extra}>{text}</td>')
        rows.append(f"<tr{attributes}>{''.join(cells)}</tr>")
    kind = ' class="sortable"' if block.sortable else ""
    identity = f' id="{block.id}"' if block.id else ""
    text = (
        f'<div class="scroll"><table{kind}{identity}><thead><tr>{head}</tr></thead>'
        f"<tbody>\n{chr(10).join(rows)}\n</tbody></table></div>"
    )
    if block.folded:
        return f'<details class="table"><summary>{inline(html.escape(block.folded))}</summary>\n{text}\n</details>'
    return text


def block(item) -> str:
    if isinstance(item, Text):
        return paragraphs(item.markdown)
    if isinstance(item, Table):
        return table(item)
    if isinstance(item, Figure):
        keys = "".join(
            f' data-{key}="{html.escape(value)}"'
            for key, value in (("system", item.system), ("regime", item.regime))
            if value
        )
        source = f"figures/{item.name}.svg"
        return (
            f'<figure{keys}><a href="{source}"><img src="{source}" '
            f'alt="{html.escape(item.alt)}"></a></figure>'
        )
    if isinstance(item, Code):
        return f"<pre>{html.escape(item.text)}</pre>"
    raise TypeError(f"no HTML for {type(item).__name__}")


def section(part: Section) -> str:
    """A section; the figures of one cell (a system's trajectory) stand beside its tables
    where the page is wide enough, every other figure (a heat map over all cells, a
    scaling plot) below them at the page's full width, so that its labels stay legible."""
    blocks = shown(part.blocks, HTML)
    figures = [item for item in blocks if isinstance(item, Figure) and item.system]
    wide = [item for item in blocks if isinstance(item, Figure) and not item.system]
    others = [block(item) for item in blocks if not isinstance(item, Figure)]
    body = "\n".join(others)
    if figures:
        pictures = "\n".join(map(block, figures))
        body = f'<div class="beside"><div class="main">{body}</div><div class="figures">{pictures}</div></div>'
    if wide:
        body += '\n<div class="wide">' + "\n".join(map(block, wide)) + "</div>"
    title = inline(html.escape(part.title))
    if part.folded:
        return f"<details>\n<summary>{title}</summary>\n{body}\n</details>"
    heading = f"<h{part.level}>{title}</h{part.level}>\n" if part.title else ""
    return f"<section>\n{heading}{body}\n</section>"


def _options(choices: dict[str, str]) -> str:
    return "".join(
        f'<option value="{html.escape(key)}">{html.escape(title)}</option>'
        for key, title in choices.items()
    )


def document(title: str, sections: list[Section], filters: dict[str, dict[str, str]]) -> str:
    """The page: ``title``, the sections (tabbed ones in panels, one per tab, the first
    shown), and ``filters`` (``system`` and ``regime``: value -> title) above the panels."""
    tabs = list(dict.fromkeys(part.tab for part in sections if part.tab))
    first = next((i for i, part in enumerate(sections) if part.tab), len(sections))
    last = max((i for i, part in enumerate(sections) if part.tab), default=first - 1)
    before = "\n".join(map(section, sections[:first]))
    after = "\n".join(map(section, sections[last + 1 :]))
    controls = "".join(
        f'<label>{key.capitalize()} <select id="filter-{key}"><option value="">all</option>'
        f"{_options(choices)}</select></label>"
        for key, choices in filters.items()
    )
    buttons = "".join(
        f'<button type="button" class="tab" data-tab="{html.escape(tab)}">{html.escape(tab)}</button>'
        for tab in tabs
    )
    panels = "\n".join(
        f'<div class="panel" data-tab="{html.escape(tab)}"{" hidden" if number else ""}>\n'
        + "\n".join(section(part) for part in sections[first : last + 1] if part.tab == tab)
        + "\n</div>"
        for number, tab in enumerate(tabs)
    )
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{html.escape(title)}</title>
<style>{STYLE}</style>
<script>{SCRIPT}</script>
</head>
<body>
<h1>{inline(html.escape(title))}</h1>
{before}
<nav class="tabs" aria-label="tracks">Track: {buttons}</nav>
<div class="controls">{controls} <span class="hint">Open a long table (Every cell, ...) and click a column header to sort it.</span></div>
{panels}
{after}
</body>
</html>
"""


STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5rem auto; max-width: 1400px; color: #222; padding: 0 1rem; }
table { border-collapse: collapse; font-size: 0.82rem; margin: 0.5rem 0 1.2rem; }
th, td { border-bottom: 1px solid #ddd; padding: 0.2rem 0.45rem; text-align: right; }
th { background: #f4f4f4; position: sticky; top: 0; }
table.sortable th { cursor: pointer; user-select: none; }
th.sorted-asc::after { content: " \\25B2"; } th.sorted-desc::after { content: " \\25BC"; }
td.text, th.text { text-align: left; white-space: pre-line; }
td.best { font-weight: bold; } td.tied { font-style: italic; }
nav.tabs { position: sticky; top: 0; background: #fff; padding: 0.5rem 0; z-index: 2; border-bottom: 2px solid #ccc; }
button.tab { font: inherit; margin-right: 0.3rem; padding: 0.25rem 0.7rem; border: 1px solid #bbb; background: #f4f4f4; cursor: pointer; }
button.tab.active { background: #2b5797; color: #fff; border-color: #2b5797; }
.controls { margin: 0.6rem 0; } .controls label { margin-right: 1rem; } .hint { color: #666; }
.beside { display: flex; flex-wrap: wrap; gap: 1rem; align-items: flex-start; }
.beside .main { flex: 1 1 900px; min-width: 0; overflow-x: auto; } .beside .figures { flex: 1 1 400px; }
img { max-width: 100%; } figure { margin: 0 0 1rem; } .wide img { width: 100%; }
pre { background: #f4f4f4; padding: 0.6rem; overflow-x: auto; }
details { margin: 0.5rem 0; } details summary { cursor: pointer; font-weight: 600; font-size: 1.1rem; }
details.table summary { font-size: 0.95rem; }
.scroll { overflow-x: auto; max-width: 100%; }
.scroll.overflows { box-shadow: inset -12px 0 10px -10px #888; }
.scroll.overflows::before { content: "\\21E2  wider than the page: scroll sideways for the other columns"; display: block; position: sticky; left: 0; color: #a33; font-size: 0.8rem; }
"""

SCRIPT = """
function sortTable(header) {
  const table = header.closest("table");
  const body = table.tBodies[0];
  const index = Array.from(header.parentNode.children).indexOf(header);
  const ascending = !header.classList.contains("sorted-asc");
  table.querySelectorAll("th").forEach(th => th.classList.remove("sorted-asc", "sorted-desc"));
  header.classList.add(ascending ? "sorted-asc" : "sorted-desc");
  const key = row => {
    const cell = row.children[index];
    const value = cell.dataset.value !== undefined ? cell.dataset.value : cell.textContent;
    const number = parseFloat(value);
    return isNaN(number) ? value : number;
  };
  const rows = Array.from(body.rows);
  rows.sort((a, b) => {
    const x = key(a), y = key(b);
    if (typeof x === "number" && typeof y === "number") return ascending ? x - y : y - x;
    return ascending ? String(x).localeCompare(String(y)) : String(y).localeCompare(String(x));
  });
  rows.forEach(row => body.appendChild(row));
}
function applyFilters() {
  const value = key => { const select = document.getElementById("filter-" + key); return select ? select.value : ""; };
  const system = value("system"), regime = value("regime");
  document.querySelectorAll("tr[data-system]").forEach(row => {
    row.hidden = (system && row.dataset.system !== system) ||
                 (regime && row.dataset.regime && row.dataset.regime !== regime);
  });
  document.querySelectorAll("figure[data-system]").forEach(figure => {
    figure.hidden = (system && figure.dataset.system !== system) ||
                    (regime && figure.dataset.regime !== regime);
  });
}
function markOverflows() {
  document.querySelectorAll("div.scroll").forEach(box => {
    box.classList.toggle("overflows", box.scrollWidth > box.clientWidth + 1);
  });
}
function showTab(name) {
  document.querySelectorAll("div.panel").forEach(panel => { panel.hidden = panel.dataset.tab !== name; });
  document.querySelectorAll("button.tab").forEach(button => {
    button.classList.toggle("active", button.dataset.tab === name);
  });
  markOverflows();
}
document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("table.sortable th").forEach(th =>
    th.addEventListener("click", () => sortTable(th)));
  document.querySelectorAll("select[id^=filter-]").forEach(select =>
    select.addEventListener("change", applyFilters));
  const buttons = document.querySelectorAll("button.tab");
  buttons.forEach(button => button.addEventListener("click", () => showTab(button.dataset.tab)));
  document.querySelectorAll("details").forEach(details =>
    details.addEventListener("toggle", markOverflows));
  window.addEventListener("resize", markOverflows);
  if (buttons.length) showTab(buttons[0].dataset.tab);
  markOverflows();
});
"""
