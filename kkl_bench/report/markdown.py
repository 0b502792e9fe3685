"""Sections (:mod:`kkl_bench.analysis.document`) as GitHub Markdown."""

from __future__ import annotations

import pandas as pd
from tabulate import tabulate

from kkl_bench.analysis.document import MARKDOWN, Code, Figure, Section, Table, Text, shown

MARKUP = {"best": ("**", "**"), "tied": ("*", "*")}


def marked(frame: pd.DataFrame, marks: pd.DataFrame | None, markup=MARKUP) -> pd.DataFrame:
    """``frame`` with each marked cell's text wrapped in ``markup[mark]``; numbers in
    marked cells are written as text by ``str``."""
    if marks is None:
        return frame
    out = frame.astype(object).copy()
    for column in frame.columns:
        for index, mark in marks[column].items():
            if mark:
                before, after = markup[mark]
                out.at[index, column] = f"{before}{frame.at[index, column]}{after}"
    return out


def table(block: Table) -> str:
    """A GitHub table; numbers are formatted (``floatfmt``, ``intfmt``) and right-aligned
    only in a table with numeric columns: a table of texts shows them as they are."""
    numeric = any(is_number_column(block.frame[column]) for column in block.headers)
    frame = marked(block.frame, block.marks)[list(block.headers)]
    return tabulate(
        frame.astype(object).where(frame.notna(), None),
        headers=list(block.headers.values()),
        tablefmt="github",
        floatfmt=block.floatfmt,
        intfmt=block.intfmt,
        showindex=False,
        missingval="",
        disable_numparse=not numeric,
    )


def is_number_column(column: pd.Series) -> bool:
    return pd.api.types.is_numeric_dtype(column) and not pd.api.types.is_bool_dtype(column)


def block(item) -> str:
    if isinstance(item, Text):
        return item.markdown
    if isinstance(item, Table):
        return table(item)
    if isinstance(item, Figure):
        return f"![{item.alt}](figures/{item.name}.png)"
    if isinstance(item, Code):
        return f"```bash\n{item.text}\n```"
    raise TypeError(f"no Markdown for {type(item).__name__}")


def section(part: Section) -> str:
    heading = [f"{'#' * part.level} {part.title}"] if part.title else []
    return "\n\n".join([*heading, *(block(item) for item in shown(part.blocks, MARKDOWN))])


def document(title: str, sections: list[Section]) -> str:
    """The whole Markdown file: ``# title``, then every section that shows anything in
    Markdown (a page-only section, such as a panel drawn from a file beside the board, is
    left out)."""
    kept = [part for part in sections if not part.blocks or shown(part.blocks, MARKDOWN)]
    return "\n\n".join([f"# {title}", *map(section, kept)]) + "\n"
