"""Whitespace-separated numeric tables in blank-line separated blocks (ASTER V003 text
tables, ASP camera XML elements)."""

from __future__ import annotations


class TableError(ValueError):
    """A line of a numeric table that is not numbers (``line`` holds it)."""

    def __init__(self, line: str):
        super().__init__(line)
        self.line = line


def numeric_blocks(text: str) -> list:
    """Blocks of rows of floats: ``[[row, ...], ...]``, blocks separated by blank lines.

    Raises :class:`TableError` naming the first line that is not numbers.
    """
    blocks, cur = [], []
    for line in text.replace("\r", "").split("\n"):
        s = line.strip()
        if not s:
            if cur:
                blocks.append(cur)
                cur = []
            continue
        try:
            cur.append([float(x) for x in s.split()])
        except ValueError:
            raise TableError(s) from None
    if cur:
        blocks.append(cur)
    return blocks
