"""One-screen summaries of result objects: ``repr`` in a terminal, an HTML table in a notebook.

A result class lists what matters in a :class:`Summary` (a title, labelled lines, an optional
table and the attributes to look at next) from its ``_summary`` method; :class:`Summarised`
turns that into ``__repr__`` and ``_repr_html_``. The class's dataclass decorator takes
``repr=False`` so that its own field-by-field repr (hundreds of kilobytes of arrays) does not
replace it.
"""

from __future__ import annotations

import html
from dataclasses import dataclass

__all__ = ["Summary", "Summarised", "table_of", "counts"]

MAX_ROWS = 16  # table rows shown (the paper's 16 DUs fit); more are elided in the middle
MAX_COLWIDTH = 18  # characters per table cell


@dataclass(frozen=True)
class Summary:
    """What a result shows of itself.

    title : one line naming the object; lines : (label, text) pairs; table : a pandas
    DataFrame or None, shown under ``table_title``; more : the attributes to look at next.
    """

    title: str
    lines: tuple[tuple[str, str], ...] = ()
    table: object | None = None
    table_title: str = ""
    more: str = ""

    def text(self) -> str:
        out = [self.title]
        width = max((len(k) for k, _ in self.lines), default=0)
        out += [f"  {k.ljust(width)}  {v}" for k, v in self.lines]
        if self.table is not None and len(self.table):
            import pandas as pd

            with pd.option_context("display.width", 100, "display.max_columns", 12):
                body = self.table.to_string(index=False, max_rows=MAX_ROWS,
                                            max_colwidth=MAX_COLWIDTH, float_format=_num)
            out += [f"{self.table_title}:" if self.table_title else "", body]
        if self.more:
            out.append(self.more)
        return "\n".join(x for x in out if x != "")

    def html(self) -> str:
        rows = "".join(f"<tr><th style='text-align:left'>{html.escape(k)}</th>"
                       f"<td style='text-align:left'>{html.escape(v)}</td></tr>"
                       for k, v in self.lines)
        out = [f"<p><b>{html.escape(self.title)}</b></p>"]
        if rows:
            out.append(f"<table>{rows}</table>")
        if self.table is not None and len(self.table):
            if self.table_title:
                out.append(f"<p>{html.escape(self.table_title)}:</p>")
            out.append(self.table.to_html(index=False, max_rows=MAX_ROWS, float_format=_num,
                                          border=0))
        if self.more:
            out.append(f"<p><code>{html.escape(self.more)}</code></p>")
        return "\n".join(out)


class Summarised:
    """Mixin: ``repr`` and a notebook's HTML from the class's ``_summary()``."""

    def _summary(self) -> Summary:  # pragma: no cover - every subclass has one
        raise NotImplementedError

    def __repr__(self) -> str:
        return self._summary().text()

    def _repr_html_(self) -> str:
        return self._summary().html()


def _num(x: float) -> str:
    return f"{x:.4g}"


def table_of(df, prefer: tuple[str, ...]):
    """The columns of ``df`` among ``prefer`` (in that order), or its first six when none."""
    if df is None:
        return None
    cols = [c for c in prefer if c in df.columns] or list(df.columns[:6])
    return df[cols]


def counts(items, noun: str) -> str:
    """'3 takes (rest 1, response 2)' from an iterable of kinds."""
    items = list(items)
    by: dict[str, int] = {}
    for k in items:
        by[str(k)] = by.get(str(k), 0) + 1
    inner = ", ".join(f"{k} {n}" for k, n in by.items())
    return f"{len(items)} {noun}" + (f" ({inner})" if inner else "")
