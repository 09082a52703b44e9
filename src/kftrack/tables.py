"""Tables for the chapters: an HTML table on the page, aligned plain text everywhere else.

A chapter that prints a table with ``print`` gets a block of monospaced text that runs off a
narrow page; :class:`Table` displays as a real HTML table in Jupyter and on the site, while
its plain-text form (what nbval compares and a terminal shows) stays aligned columns.
Presentation layer: no numerics here.
"""
from __future__ import annotations

import html
from collections.abc import Sequence

__all__ = ["Table"]


class Table:
    """A small table of already computed values.

    Parameters
    ----------
    rows : sequence of sequences
        One entry per row, each with one value per column.
    header : sequence of str
        The column titles.
    formats : sequence of str or None, optional
        One format specification per column (e.g. ``".3f"``, ``".2e"``, ``""``); ``None``
        formats every value with ``str``.
    caption : str, optional
        Shown above the table.

    Examples
    --------
    >>> Table([["CV", 12.3456], ["IMM", 8.9]], ["filter", "RMSE (m)"], formats=["", ".1f"])
    filter  RMSE (m)
    ------  --------
    CV          12.3
    IMM          8.9
    """

    def __init__(self, rows: Sequence[Sequence], header: Sequence[str], *,
                 formats: Sequence[str] | None = None, caption: str | None = None):
        header = [str(h) for h in header]
        if not header:
            raise ValueError("header must name at least one column")
        if formats is not None and len(formats) != len(header):
            raise ValueError(f"formats must give one format per column ({len(header)}), got {len(formats)}")
        cells = []
        for i, row in enumerate(rows):
            row = list(row)
            if len(row) != len(header):
                raise ValueError(f"rows[{i}] has {len(row)} values, expected {len(header)} (one per header column)")
            cells.append([format(v, formats[j]) if formats else str(v) for j, v in enumerate(row)])
        self.header, self.cells, self.caption = header, cells, caption

    def _numeric(self, j: int) -> bool:
        def number(s: str) -> bool:
            try:
                float(s.replace("%", "").replace("×", ""))
                return True
            except ValueError:
                return False
        return bool(self.cells) and all(number(r[j]) for r in self.cells)

    def __repr__(self) -> str:
        widths = [max([len(h)] + [len(r[j]) for r in self.cells]) for j, h in enumerate(self.header)]
        right = [self._numeric(j) for j in range(len(self.header))]

        def line(values):
            return "  ".join(v.rjust(w) if r else v.ljust(w) for v, w, r in zip(values, widths, right)).rstrip()

        out = ([self.caption] if self.caption else []) + [line(self.header), line(["-" * w for w in widths])]
        return "\n".join(out + [line(r) for r in self.cells])

    def _repr_html_(self) -> str:
        right = [self._numeric(j) for j in range(len(self.header))]

        def cell(tag: str, v: str, r: bool) -> str:
            return f'<{tag} style="text-align:{"right" if r else "left"}">{html.escape(v)}</{tag}>'

        head = "".join(cell("th", h, r) for h, r in zip(self.header, right))
        body = "".join("<tr>" + "".join(cell("td", v, r) for v, r in zip(row, right)) + "</tr>" for row in self.cells)
        cap = f"<caption>{html.escape(self.caption)}</caption>" if self.caption else ""
        return f'<table class="kftrack-table">{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'
