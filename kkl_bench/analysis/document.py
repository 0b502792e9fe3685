"""The published board as data: sections of text, tables and figures, rendered twice.

A :class:`Section` holds blocks; :mod:`kkl_bench.report.markdown` and
:mod:`kkl_bench.report.html` turn the same list of sections into
``README.md`` and ``index.html``. A block shown in one rendering only says so
(``only``): the page's sortable long tables are too long for the README, and
the README's links to the PNG figures have the page's SVGs as their twins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pandas as pd

MARKDOWN, HTML = "markdown", "html"


@dataclass(frozen=True)
class Text:
    """Paragraphs of inline Markdown (code, bold, italics, links), separated by blank lines."""

    markdown: str
    only: str | None = None


@dataclass(frozen=True)
class Table:
    """A table: ``frame``'s columns (``columns``: column -> header; default every column
    under its own name), its cells strings or numbers.

    marks: the cells' significance marks, ``best``, ``tied`` or empty, aligned with
        ``frame`` (bold and italics in both renderings).
    shades: per cell, how far it is from the best possible, as a ratio >= 1 (NaN for
        none); the page colours the cell by it.
    floatfmt, intfmt: how numbers are written.
    sortable: the page sorts it by any column and filters its rows by the frame's
        ``system`` and ``regime`` columns (raw names), if it has them.
    folded: if set, the page shows only this line until clicked (a long table that
        would otherwise push what follows it out of sight).
    """

    frame: pd.DataFrame
    columns: dict[str, str] | None = None
    id: str = ""
    marks: pd.DataFrame | None = None
    shades: pd.DataFrame | None = None
    floatfmt: str = ".3g"
    intfmt: str = ""
    sortable: bool = False
    only: str | None = None
    folded: str = ""

    @property
    def headers(self) -> dict[str, str]:
        return self.columns if self.columns is not None else {c: c for c in self.frame.columns}


@dataclass(frozen=True)
class Figure:
    """A figure drawn into ``figures/<name>.png`` and ``.svg``; the page's filters hide it
    when it shows another ``system`` or ``regime`` than they select."""

    name: str
    alt: str
    only: str | None = None
    system: str = ""
    regime: str = ""


@dataclass(frozen=True)
class Code:
    """A block of shell commands."""

    text: str
    only: str | None = None


Block = Text | Table | Figure | Code


@dataclass(frozen=True)
class Section:
    """A titled part of the board (an empty title: no heading). ``tab``: the page shows
    the section in the panel of that name (one per track); sections without a tab stand
    above or below the panels. ``folded``: the page shows only its title until clicked
    (for what a reader needs once, such as how to read the tables)."""

    title: str
    blocks: list[Block] = field(default_factory=list)
    level: int = 2
    tab: str | None = None
    folded: bool = False


def shown(blocks: list[Block], rendering: str) -> list[Block]:
    """The blocks ``rendering`` (:data:`MARKDOWN` or :data:`HTML`) shows."""
    return [block for block in blocks if block.only in (None, rendering)]
