"""Tiles of the left (reference) image: the unit of work of the stereo stage.

A tile is a rectangle of pixel centres ``col0 .. col0 + cols - 1`` by ``row0 .. row0 + rows - 1``
with its position ``index`` in the plan (tile order fixes the order in which the tiles' cell
sums are added, so the DEM does not depend on how tiles are scheduled). Rectification adds
its own halo around a tile; only the tile's own points are kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["Tile", "tile_grid"]


@dataclass(frozen=True)
class Tile:
    """A rectangle of the left image (pixels; centre of the top-left pixel at (0, 0))."""

    col0: int
    row0: int
    cols: int
    rows: int
    index: int = 0

    @property
    def bounds(self):
        """``(col_min, row_min, col_max, row_max)`` of pixel centres, inclusive."""
        return (self.col0, self.row0, self.col0 + self.cols - 1, self.row0 + self.rows - 1)

    @property
    def size(self) -> int:
        """Number of pixels."""
        return self.cols * self.rows

    def contains(self, col, row):
        """Boolean mask of points whose nearest pixel lies in the tile."""
        c0, r0, c1, r1 = self.bounds
        return (col >= c0 - 0.5) & (col < c1 + 0.5) & (row >= r0 - 0.5) & (row < r1 + 0.5)

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "col0": self.col0,
            "row0": self.row0,
            "cols": self.cols,
            "rows": self.rows,
        }


def tile_grid(width: int, height: int, tile_size: int, *, window=None) -> list[Tile]:
    """Split an image of ``width`` x ``height`` pixels (or the ``window = (col0, row0, col1,
    row1)`` part of it) into tiles of about ``tile_size`` pixels square, of nearly equal size,
    covering the window exactly, numbered row-major from 0.
    """
    c0, r0, c1, r1 = window if window is not None else (0, 0, width - 1, height - 1)
    c0, r0 = max(int(np.floor(c0)), 0), max(int(np.floor(r0)), 0)
    c1, r1 = min(int(np.ceil(c1)), width - 1), min(int(np.ceil(r1)), height - 1)
    if c1 < c0 or r1 < r0:
        return []

    def edges(a, b):
        n = max(1, int(round((b - a + 1) / tile_size)))
        return np.linspace(a, b + 1, n + 1).round().astype(int)

    ce, re = edges(c0, c1), edges(r0, r1)
    tiles = [
        Tile(int(ce[i]), int(re[j]), int(ce[i + 1] - ce[i]), int(re[j + 1] - re[j]))
        for j in range(len(re) - 1)
        for i in range(len(ce) - 1)
    ]
    return renumber(tiles)


def tile_order(tiles) -> list[Tile]:
    """The order in which tiles are run and their sums added: largest first (the tiles at the
    scene's edges are smaller, so no worker of a pool is left with a big tile while the others
    idle), ties by index. One order for every runner and worker count, so the DEM's float
    sums do not depend on them, and close to the order a pool finishes the tiles in, so their
    sums can be added while the pool runs."""
    return sorted(tiles, key=lambda t: (-t.size, t.index))


def renumber(tiles) -> list[Tile]:
    """The tiles with ``index`` set to their position in the list."""
    return [replace(t, index=k) for k, t in enumerate(tiles)]
