"""Result tables as files the documentation includes: one Markdown table plus the same rows as CSV.

``write_table(rows, path)`` writes ``path`` with the suffix ``.md`` (an optional title and notes,
then a pipe table) and ``.csv`` (the rows, full precision), both atomically, so a generated table is
never hand-copied into a page: the docs include the ``.md`` file.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from togglecf.core.io import atomic_write_text

__all__ = ["write_table", "markdown_table"]


def _cell(v, digits: int) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isnan(v):
            return ""
        return f"{v:.{digits}f}"
    return str(v)


def markdown_table(rows: list[dict], columns=None, digits: int = 3) -> str:
    """A pipe table of ``rows`` (dicts) with ``columns`` (default: the first row's keys), floats
    to ``digits`` decimals, missing values blank."""
    columns = list(columns or (rows[0].keys() if rows else ()))
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(c), digits) for c in columns) + " |")
    return "\n".join(lines)


def write_table(rows: list[dict], path, columns=None, title: str | None = None, notes=(), digits: int = 3) -> dict:
    """Write ``path.md`` (``# title``, the notes as paragraphs, the table) and ``path.csv``
    (``columns`` of every row, unrounded). Returns ``{"md": Path, "csv": Path}``."""
    path = Path(path)
    md, cv = path.with_suffix(".md"), path.with_suffix(".csv")
    columns = list(columns or (rows[0].keys() if rows else ()))
    parts = [f"# {title}", ""] if title else []
    for n in notes:
        parts += [n, ""]
    parts += [markdown_table(rows, columns, digits), ""]
    atomic_write_text(md, "\n".join(parts))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: ("" if r.get(c) is None else r.get(c)) for c in columns})
    atomic_write_text(cv, buf.getvalue())
    return {"md": md, "csv": cv}
