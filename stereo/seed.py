"""Seed disparity maps: holes filled along the rows by the background (the smaller of the
nearest valid neighbours), rows without a valid value column-wise, then a 5 x 5 median; and
the same on whole pixels (rounded first: rounding commutes with the fill and the median)
for the score layer's warp."""

from __future__ import annotations

import cv2
import numpy as np

F32 = np.float32


def _fill_rows(d):
    """NaN -> the smaller (background) of the nearest valid values left and right.

    Only the NaN cells are visited: each run of consecutive NaN cells (in row-major order)
    takes the cells just before and after the run, when they lie in the same row."""
    h, w = d.shape
    out = np.ascontiguousarray(d).ravel().copy()
    _fill_row_runs(out, np.flatnonzero(~np.isfinite(out)), w)
    return out.reshape(h, w)


def _fill_row_runs(flat, holes, w):
    """:func:`_fill_rows` in place on a flattened map of rows of ``w`` cells, given the flat
    indices ``holes`` (ascending) of all its non-finite cells; returns the holes left NaN
    (those of rows without any valid cell)."""
    if holes.size == 0 or holes.size == flat.size:
        return holes
    brk = np.flatnonzero(np.diff(holes) != 1)
    starts = np.concatenate([[0], brk + 1])  # first hole of each run
    ends = np.concatenate([brk, [holes.size - 1]])  # last hole of each run
    run = np.repeat(np.arange(starts.size), ends - starts + 1)
    li = holes[starts][run] - 1  # the valid cell before the run
    ri = holes[ends][run] + 1  # ... and after it
    row = holes // w
    left = np.where((li >= 0) & (li // w == row), flat[np.maximum(li, 0)], np.nan)
    right = np.where(
        (ri < flat.size) & (ri // w == row), flat[np.minimum(ri, flat.size - 1)], np.nan
    )
    with np.errstate(invalid="ignore"):
        vals = np.fmin(left, right)
    flat[holes] = vals
    return holes[np.isnan(vals)]


def _fill_seed(d, fallback):
    """Fill NaN in a disparity map for use as a seed, then a 5x5 median.

    Along rows, a hole takes the smaller (background) of its nearest valid neighbours
    (occlusions belong to the background); rows without any valid value take their nearest
    valid rows (column-wise), and an all-NaN map takes ``fallback``."""
    d = np.asarray(d, dtype=F32)
    if not np.isfinite(d).all():
        d = _fill_seed_holes(d, fallback)
    return cv2.medianBlur(np.ascontiguousarray(d, dtype=F32), 5)


def _fill_seed_holes(d, fallback):
    """The hole filling of :func:`_fill_seed` (a new array)."""
    d = _fill_rows(d)
    if not np.isfinite(d).all():
        d = _fill_columns(d, fallback)
    return d


def _fill_columns(d, fallback):
    """The second step of :func:`_fill_seed_holes`, for rows without any valid value: the
    column-wise fill, then ``fallback`` (a new array)."""
    d = np.ascontiguousarray(_fill_rows(np.ascontiguousarray(d.T)).T)
    d[~np.isfinite(d)] = fallback
    return d


def _rounded_filled(d, holes=None):
    """``np.rint(_fill_seed_holes(d, 0.0))`` (a new array) and its min and max.

    The rounding comes first and the holes are filled in the rounded copy: rounding is
    monotone, so it commutes with the fill's minimum of two neighbours.  ``holes``: the flat
    indices (ascending) of ``d``'s non-finite cells when the caller has them (None: found
    here)."""
    d = np.asarray(d, dtype=F32)
    r = np.rint(d, out=np.empty(d.shape, F32))
    if holes is None:
        holes = np.flatnonzero(~np.isfinite(r))
    if holes.size and _fill_row_runs(r.ravel(), holes, d.shape[1]).size:
        r = _fill_columns(r, 0.0)
    lo, hi = cv2.minMaxLoc(r)[:2]
    return r, lo, hi


def _median_offset(r, lo, hi):
    """The 5x5 median of a rounded seed ``r`` (whole pixels in ``lo..hi``) as
    ``(base, median - base)``: rounding is monotone, so it commutes with the median; on small
    integers (a span of at most 255) OpenCV's uint8 median is twice as fast as the float32 one
    (``base = lo``, the second term uint8), else ``base = 0`` and a float32 median."""
    if hi - lo > 255:
        return 0.0, cv2.medianBlur(r, 5)
    small = cv2.convertScaleAbs(r, alpha=1.0, beta=-lo)  # r - lo: whole numbers 0..255, exact
    return lo, cv2.medianBlur(small, 5)
