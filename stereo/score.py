"""The score layer: the ZNCC of each left window with the right image warped by a given
disparity (:func:`zncc_at`; the ``"sgm"`` matcher's score), by row bands of
:data:`SCORE_BAND_ROWS` rows with their halos, each centred by its own levels."""

from __future__ import annotations

import functools
from typing import NamedTuple

import cv2
import numpy as np

from stereodem.core.blocks import each_fixed_band
from stereodem.core.morphology import square_dilation

from .images import _as_image, _col_index
from .seed import _median_offset, _rounded_filled
from .window_stats import _TINY, _box_mean, _floor_row, _nan_border, _window_stats

F32 = np.float32


def zncc_at(left, right, disparity, *, window=7):
    """ZNCC of each left window with the right image warped by ``disparity``.

    The right window of pixel ``x`` is made of the right pixels ``x' - s(x')`` for ``x'``
    in the left window (the window follows the disparity surface), where ``s`` is the
    disparity rounded to whole pixels with its NaN filled from their row neighbours, then
    smoothed by a 5 x 5 median (:func:`_seed_columns`: a lone outlier does not tear the
    warp); the score of a NaN disparity is NaN.

    Returns
    -------
    ndarray (H, W), float32, in [-1, 1]; NaN at no-data, flat windows and image borders.
    """
    left = _as_image(left, "left")
    right = _as_image(right, "right")
    return _zncc_warped(_zncc_left(left, window), right, disparity)


def _seed_columns(d, w, holes=None):
    """The score layer's warp: ``x - np.rint(_fill_seed(d, 0.0))`` as float32 (the remap's
    column map, whole pixels), in one pass from the uint8 median when the seed's span allows
    (integers: exact either way), and the rounded seed's min and max (pixels: the map lies in
    ``x - max .. x - min``).  ``holes``: :func:`_rounded_filled`'s."""
    r, lo, hi = _rounded_filled(d, holes)
    base, med = _median_offset(r, lo, hi)
    m = med.astype(F32, copy=False)  # a fresh array either way: the map is built in it
    return np.subtract(np.subtract(_col_index(w), F32(base)), m, out=m), lo, hi


def _outside_windows(map_x, lo, hi, window):
    """The windows (side ``window``) of a warp by ``map_x`` (whole pixels, in
    ``x - hi .. x - lo``) that contain a pixel mapped outside the image (``map_x < 0`` or
    ``> w - 1``), as ``(columns, mask)`` pairs for :func:`_window_stats`: such pixels can only
    lie in the first ``hi`` and the last ``-lo`` columns, so the mask and its dilation are
    computed on those strips (plus the window's reach), not on the whole image."""
    h, w = window // 2, map_x.shape[1]
    a = int(hi) + 2 * h + 1 if hi > 0 else 0  # strip [0, a): pixels with map_x < 0 and reach
    b = w - 1 + int(lo) - 2 * h if lo < 0 else w  # strip [b, w): map_x > w - 1 and reach
    if a >= b:  # the strips meet: the whole image
        return [(slice(None), _dilated_outside(map_x, w, window))]
    out = []
    if a > 0:  # exact for windows centred left of a - h (the rest see no such pixel)
        keep = a - h
        out.append((slice(0, keep), _dilated_outside(map_x[:, :a], w, window)[:, :keep]))
    if b < w:
        keep = b + h
        out.append((slice(keep, w), _dilated_outside(map_x[:, b:], w, window)[:, h:]))
    return out


def _dilated_outside(map_x, w, window):
    """Boolean mask of the ``window`` x ``window`` windows containing a ``map_x`` outside
    ``0 .. w - 1`` (``w``: the image width; ``map_x``: the whole map or a strip of whole
    columns of it, zero padding at its edges)."""
    return square_dilation((map_x < 0) | (map_x > w - 1), window)


@functools.lru_cache(maxsize=4)
def _row_map(h, w):
    """Row coordinates as an (h, w) float32 ``cv2.remap`` map (read-only, cached per shape:
    rebuilding it costs as much as the remap itself)."""
    a = np.repeat(np.arange(h, dtype=F32)[:, None], w, axis=1)
    a.flags.writeable = False
    return a


class _LeftWindows(NamedTuple):
    """What the score layer needs of the left image before the disparity: its centring
    constant; the window statistics are computed band by band with the warped part
    (:func:`_zncc_warped`), while the band is in cache."""

    off: np.float32  # the image's mean (centring constant)
    window: int
    left: np.ndarray  # the image itself
    finite: bool  # whether ``left - off`` has no NaN


#: rows of a band of the score layer (computed with its halo of ``window // 2`` rows each
#: side, :func:`_halo`): the band's arrays stay in a core's cache between the box filters and
#: the element-wise passes, and the bands can run on several threads
#: (:func:`stereodem.core.blocks.each_fixed_band`); fixed, so the score does not depend on the
#: thread count
SCORE_BAND_ROWS = 128


def _halo(r0: int, r1: int, n_rows: int, window: int) -> tuple[int, int]:
    """Input rows ``a:b`` of the score's output rows ``r0:r1``: the band and ``window // 2``
    rows each side, within the image; every kept row's window lies inside them, so a band's
    values are those of the whole image."""
    h = window // 2
    return max(r0 - h, 0), min(r1 + h, n_rows)


def _zncc_left(left, window, finite=None, mean=None):
    """The left image's part of the score layer (:class:`_LeftWindows`); ``finite``: whether
    ``left`` is known to have no NaN (None: scan it); ``mean``: ``np.mean(left)`` when the
    caller has it (:func:`_image_and_finite`; ``left`` finite and C-contiguous)."""
    # without no-data, np.mean of a C-contiguous image sums in the same (pairwise) order as
    # np.nanmean, so it gives the same float32, in one pass instead of three
    if mean is not None:
        finite, off = True, mean
    else:
        if finite is None:
            finite = bool(np.isfinite(left).all())
        off = np.mean(left) if finite and left.flags.c_contiguous else np.nanmean(left)
    # a finite image minus a finite constant below 1e30 stays finite (no overflow)
    finite = finite and bool(np.isfinite(off)) and abs(float(off)) < 1e30
    return _LeftWindows(off, window, left, finite)


def _level(sample, fallback, finite=False) -> np.float32:
    """A centring constant of the score layer: the mean of the finite values of ``sample``
    (float32; every 4th row of a band), else ``fallback``. ``finite=True``: ``sample`` is
    known to have no NaN.

    Every window of a band's output rows lies in the band's rows, and ZNCC does not change
    when a constant is taken from an image, so any constant gives the same score in exact
    arithmetic; in float32, ``E[x^2] - E[x]^2`` loses the digits of ``x``'s distance to the
    constant, and each image's own level in the band keeps that distance small where the
    brightness changes from band to band or the two images sit at different levels (half a
    scene 2000 DN brighter: scores off by up to 0.1 away from the step with the left image's
    mean alone, 1.2e-4 with the bands' own levels)."""
    if not finite:
        sample = sample[np.isfinite(sample)]
    c = np.mean(sample, dtype=F32) if sample.size else fallback
    return F32(c) if np.isfinite(c) and abs(float(c)) < 1e30 else F32(fallback)


def _zncc_warped(a: _LeftWindows, right, disparity, right_finite=None, threads=1):
    """:func:`zncc_at` given the left image's part (:func:`_zncc_left`), by bands of
    :data:`SCORE_BAND_ROWS` rows on ``threads`` threads.

    ``right_finite``: whether ``right`` is known to have no NaN (None: scan it); then the
    warp is filled with a finite value outside the image and the windows reaching outside
    are located from the warp's column map (:func:`_outside_windows`), same result; with a
    left image without NaN as well, each band takes :func:`_zncc_band_finite` (the same
    operations on the same values, fewer passes) and the cells no window statistic is valid
    for (image border, windows reaching outside the right image) are set NaN once at the end.

    Each band is centred by its own levels, the left's and the right's in its rows
    (:func:`_level`), so the float32 sums keep their digits where the brightness
    changes from band to band or the two images sit at different levels."""
    d = np.asarray(disparity, dtype=F32)
    holes = np.flatnonzero(~np.isfinite(d))  # invalid disparities (flat indices)
    if holes.size == d.size:
        return np.full(right.shape, np.nan, dtype=F32)
    h, w = right.shape
    # right(x - seed(x), y): an exact gather (integer coordinates, nearest neighbour)
    map_x, lo, hi = _seed_columns(d, w, holes)
    if right_finite is None:
        right_finite = bool(np.isfinite(right).all())
    # a finite image minus a finite constant below 1e30 stays finite (see _zncc_left)
    fast = right_finite and abs(float(a.off)) < 1e30
    fused = fast and a.finite  # no NaN on either side: _zncc_band_finite
    rows_map = _row_map(h, w)
    score = np.empty((h, w), F32)

    def band(rows):
        r0, r1 = rows
        i0, i1 = _halo(r0, r1, h, a.window)
        level = _level(a.left[i0:i1:4], a.off, finite=a.finite)  # the left's, these rows
        warped = cv2.remap(
            right,
            map_x[i0:i1],
            rows_map[i0:i1],
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            # outside the image: any finite value (fast: the windows reaching there are found
            # from the map and set invalid) or NaN (then invalid through the NaN itself)
            borderValue=float(level) if fast else np.nan,
        )
        # the warped band by the right image's own level in these rows (the warp moves pixels
        # along rows only): the right image may sit at another level than the left (gains and
        # offsets of two sensors, 12- or 16-bit data), where the left's level loses digits
        level_r = _level(right[i0:i1:4], level, finite=right_finite)
        cv2.subtract(warped, float(level_r), dst=warped)  # float32 - float32, as NumPy
        keep = slice(r0 - i0, r1 - i0)
        # the band's left statistics (its own rows and halo: those of the whole image), next
        # to the warped ones while the band is in cache
        z = np.subtract(a.left[i0:i1], level, dtype=F32)
        if fused:
            _zncc_band_finite(z, warped, a.window, keep, score[r0:r1])
            return
        if fast:
            outside = _outside_windows(map_x[i0:i1], lo, hi, a.window)
            b = _window_stats(warped, a.window, 0.0, finite=True, outside=outside, inverse=False)
        else:
            b = _window_stats(warped, a.window, 0.0, inverse=False)
        s = _window_stats(z, a.window, 0.0, finite=a.finite, inverse=False)
        l_zero, l_mean, l_std = s.zero, s.mean[keep], s.inv[keep]
        prod = np.multiply(l_zero, b.zero)
        cov = _box_mean(prod, a.window)
        c, p, den = cov[keep], prod[keep], b.inv[keep]
        np.multiply(l_mean, b.mean[keep], out=p)
        np.subtract(c, p, out=c)  # E[lr] - E[l] E[r]
        # one division by the product of the two standard deviations, floored at 1e-30 (NaN,
        # where either window is invalid, propagates through the product, floor and division)
        np.multiply(den, l_std, out=den)
        np.maximum(den, _floor_row(_TINY, den.shape[1]), out=den)
        np.divide(c, den, out=c)
        np.clip(c, -1, 1, out=score[r0:r1])

    each_fixed_band(band, h, SCORE_BAND_ROWS, threads=threads)
    if fused:  # what _window_stats sets NaN in its statistics, set in the score instead
        for cols, mask in _outside_windows(map_x, lo, hi, a.window):
            score[:, cols][mask] = np.nan
        _nan_border(score, a.window // 2)
    score.ravel()[holes] = np.nan  # a fresh C-contiguous array: ravel() is a view
    return score


def _zncc_band_finite(z, warped, window, keep, out):
    """A band of the score layer where neither image has NaN: ``out`` (the band's output
    rows) = ZNCC of the windows of the left band ``z`` and the warped right band ``warped``
    (both float32, centred by their levels, the output rows ``keep`` and their halo).

    The operations of :func:`_window_stats` (``inverse=False``) on each side and of the
    score's last steps, on the same float32 values in the same order, so the same bits: the
    five window means by :func:`_box_mean` over the whole band, then ``E[x^2] - E[x]^2``, its
    square root (``cv2.sqrt``: IEEE, as ``np.sqrt``, twice as fast), ``E[lr] - E[l] E[r]``,
    the product of the standard deviations floored at 1e-30 and the division, on the output
    rows only. What :func:`_window_stats` sets NaN (image border, windows reaching outside
    the right image) is left to the caller."""
    mean_r = _box_mean(warped, window)
    buf = cv2.multiply(warped, warped)
    var_r = _box_mean(buf, window)
    mean_l = _box_mean(z, window)
    cv2.multiply(z, z, dst=buf)
    var_l = _box_mean(buf, window)
    cv2.multiply(z, warped, dst=buf)
    cov = _box_mean(buf, window)
    t, mr, ml = buf[keep], mean_r[keep], mean_l[keep]
    vr, vl, c = var_r[keep], var_l[keep], cov[keep]
    with np.errstate(invalid="ignore", divide="ignore"):
        cv2.multiply(mr, mr, dst=t)
        cv2.subtract(vr, t, dst=vr)  # E[r^2] - E[r]^2
        cv2.sqrt(vr, dst=vr)  # NaN where negative (rounding), as np.sqrt
        cv2.multiply(ml, ml, dst=t)
        cv2.subtract(vl, t, dst=vl)
        cv2.sqrt(vl, dst=vl)
        cv2.multiply(ml, mr, dst=t)
        cv2.subtract(c, t, dst=c)  # E[lr] - E[l] E[r]
        cv2.multiply(vr, vl, dst=vr)
        np.maximum(vr, _floor_row(_TINY, vr.shape[1]), out=vr)
        np.divide(c, vr, out=c)
        np.clip(c, -1, 1, out=out)
