"""Local raster operations in row bands on threads (numpy, scipy.ndimage and OpenCV release
the GIL), with the same values as one call on the whole grid.

A *local* operation is one whose output at a cell depends only on the inputs within ``halo``
rows of it (a correlation with a (2·halo+1)-row kernel, a Gaussian of radius ``halo``...).
:func:`by_rows` cuts the grid into one band per thread, runs the operation on each band plus
``halo`` rows of its neighbours, and keeps the band's own rows: every kept cell sees exactly
the inputs it sees in the whole grid (the grid's real edges stay edges), so the result is
bit-identical to the single call, whatever the number of threads.

The thread count defaults to the process's budget, read from OpenCV's thread setting
(``cv2.getNumThreads()``), which the application pins to ``--workers``
(:mod:`stereodem.core.threads`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

#: bands smaller than this many rows are not worth a thread
MIN_ROWS = 128


def default_threads() -> int:
    """The process's thread budget (OpenCV's setting, pinned by the application)."""
    return max(1, int(cv2.getNumThreads()))


def row_bands(n_rows: int, threads: int, min_rows: int = MIN_ROWS) -> list[tuple[int, int]]:
    """``[(r0, r1), ...]`` covering ``0..n_rows`` in at most ``threads`` near-equal bands of at
    least ``min_rows`` rows (one band when the grid is small)."""
    n = max(1, min(int(threads), n_rows // max(1, min_rows)))
    edges = np.linspace(0, n_rows, n + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def each_band(fn, n_rows: int, *, threads: int | None = None, min_rows: int = MIN_ROWS) -> list:
    """``fn((r0, r1))`` for each band of :func:`row_bands` of ``n_rows`` rows, on one thread
    per band (none with a single band); returns the results in band order. ``fn`` must only
    read shared arrays and write its own rows."""
    threads = default_threads() if threads is None else int(threads)
    return _on_threads(fn, row_bands(n_rows, threads, min_rows), threads)


def each_item(fn, items, *, threads: int | None = None) -> list:
    """``fn(item)`` for each of ``items`` (bins, chunks: independent pieces of work) on the
    budget's threads (none for one item or one thread); the results in the items' order."""
    threads = default_threads() if threads is None else int(threads)
    return _on_threads(fn, list(items), threads)


def _on_threads(fn, bands, threads: int) -> list:
    """``fn(band)`` for each band, on up to ``threads`` threads (none for a single band or
    thread); the results in band order."""
    if threads == 1 or len(bands) <= 1:
        return [fn(b) for b in bands]
    with ThreadPoolExecutor(min(threads, len(bands)), thread_name_prefix="stereodem-rows") as ex:
        return list(ex.map(fn, bands))


def by_rows(fn, *arrays, halo: int, threads: int | None = None, out=None, min_rows: int = MIN_ROWS):
    """``fn(*arrays)`` computed in row bands on threads (see the module docstring); ``fn`` must
    be local within ``halo`` rows and return an array with the inputs' rows (first axis).
    ``min_rows``: the smallest band worth a thread (rows of blocks, not cells, are fewer)."""
    rows = arrays[0].shape[0]

    def one(band):
        r0, r1 = band
        a0, a1 = max(0, r0 - halo), min(rows, r1 + halo)
        res = fn(*(a[a0:a1] for a in arrays))
        return band, res[r0 - a0 : r0 - a0 + (r1 - r0)]

    results = each_band(one, rows, threads=threads, min_rows=min_rows)
    if len(results) == 1:  # one band: the whole grid, as computed
        return results[0][1]
    if out is None:
        out = np.empty((rows,) + results[0][1].shape[1:], results[0][1].dtype)
    for (r0, r1), res in results:
        out[r0:r1] = res
    return out


def each_fixed_band(fn, n_rows: int, band_rows: int, *, threads: int | None = None) -> list:
    """``fn((r0, r1))`` for consecutive bands of ``band_rows`` rows (the last one shorter) on
    the budget's threads; returns the results in band order.

    Unlike :func:`each_band`, the bands do not depend on the number of threads: for an
    operation that is exact only within some reach of each cell (a nearest-valid-cell fill
    read only near the valid cells), computing the same bands on any number of threads gives
    the same result."""
    threads = default_threads() if threads is None else int(threads)
    step = max(1, int(band_rows))
    return _on_threads(fn, [(r, min(n_rows, r + step)) for r in range(0, n_rows, step)], threads)


def percentile_of_parts(parts, q: float, *, threads: int | None = None) -> float:
    """``np.percentile(np.concatenate(parts), q)`` (the linear method) of 1-D arrays of finite
    values, without concatenating or partitioning them all on one thread.

    The two order statistics the percentile interpolates between, at ranks ``i`` and
    ``i + 1`` of the ``n`` values, are among each part's ``n − i`` largest values (``q`` ≥ 50;
    its ``i + 2`` smallest below 50): each part selects those on its own thread
    (``np.partition``), and the ranks are then read from their union, which holds the
    ``n − i`` largest values of all. The interpolation is NumPy's (``(n − 1)·q/100``, the
    ``>= 0.5`` branch) in float64: the same number as ``np.percentile`` on float64 values
    (tested); on float32 values NumPy may round the difference of the two in float32 first.
    Returns a float; raises ``ValueError`` when the parts hold no value."""
    parts = [np.ravel(p) for p in parts if np.size(p)]
    n = sum(p.size for p in parts)
    if n == 0:
        raise ValueError("percentile of no values")
    vi = (n - 1) * (float(q) / 100.0)
    i = int(np.floor(vi))
    gamma = vi - i
    j = min(i + 1, n - 1)
    top = q >= 50
    m = n - i if top else j + 1  # values kept from each part

    def select(p):
        if p.size <= m:
            return p
        return np.partition(p, p.size - m)[p.size - m :] if top else np.partition(p, m - 1)[:m]

    threads = default_threads() if threads is None else int(threads)
    union = np.concatenate(_on_threads(select, parts, threads))
    k = union.size - m if top else i  # where rank i of all the values lies in the union
    ranks = (k, k + j - i)
    union.partition(ranks)
    a, b = np.float64(union[ranks[0]]), np.float64(union[ranks[1]])
    return float(numpy_lerp(a, b, np.float64(gamma)))


def numpy_lerp(a, b, gamma):
    """NumPy's interpolation between the order statistics ``a`` and ``b`` of a linear
    percentile (its ``_lerp``): ``a + (b − a)·γ``, or ``b − (b − a)·(1 − γ)`` where γ ≥ 0.5, in
    the arrays' own types (the difference in ``a``'s, the weights as given)."""
    a, b, gamma = np.asarray(a), np.asarray(b), np.asarray(gamma)
    diff = b - a
    step = diff * gamma
    out = np.add(a, step, out=np.empty(np.shape(step), np.result_type(a, step)))
    np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5, casting="unsafe")
    return out
