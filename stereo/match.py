"""Dense matching of a rectified (epipolar) stereo pair.

Convention: rows correspond, and the disparity ``d`` at left pixel ``(x, y)`` means that
``left(x, y)`` matches ``right(x - d, y)`` (OpenCV's and Middlebury's convention); with the
optional vertical search, ``left(x, y)`` matches ``right(x - d, y - v)``.  Pixel centres are
at integer coordinates, ``x`` = column, ``y`` = row.

Two matchers share one interface, :func:`match_rectified`:

``"ncc"``
    Zero-mean normalised cross-correlation (ZNCC) over a square window, computed with
    OpenCV box filters for all pixels at once, streaming over the disparities and keeping
    only best-so-far arrays (memory ~ image size x a small constant, independent of the
    disparity range).  Coarse-to-fine on a Gaussian pyramid by default: the coarsest level
    searches the whole (scaled) range; each finer level warps the search image by the
    upsampled coarse disparity and searches only ``+/- margin`` pixels around it.  Sub-pixel
    refinement by a parabola through the correlation peak and its two neighbours (or the
    symmetric "V" fit), left-right consistency check, correlation threshold, texture mask.
``"sgm"``
    OpenCV's semi-global matcher (``cv2.StereoSGBM``) with its conventions handled
    (``numDisparities`` multiple of 16, 1/16 fixed-point output, ``minDisparity`` for negative
    ranges, 8-bit input by percentile stretch, borders padded so that the first
    ``numDisparities`` columns are not lost); the score layer is the ZNCC at the SGM
    disparity.

NaN in the inputs marks no-data: a window touching no-data gives no match.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import cv2
import numpy as np

from stereodem.core.blocks import each_fixed_band, numpy_lerp
from stereodem.core.errors import InputError
from stereodem.core.morphology import square_dilation
from stereodem.core.stretch import linear_to_uint8
from stereodem.stereo.settings import MATCHERS

from .pyramid import build_pyramid, upsample_field

__all__ = ["MatchResult", "match_rectified", "zncc_at"]

F32 = np.float32
_SQRT_TINY = np.sqrt(F32(1e-30))  # the variance floor's square root, float32
_TINY = F32(1e-30)  # the floor of the score's product of two standard deviations


class MatchResult(NamedTuple):
    """Output of :func:`match_rectified`.

    Attributes
    ----------
    disparity : ndarray (H, W), float32
        ``d`` in pixels with ``left(x, y) ~ right(x - d, y - v)``; NaN where no valid match.
    score : ndarray (H, W), float32
        ZNCC in [-1, 1] of the retained match (for ``"ncc"``: the correlation peak of the
        best candidate, kept also where the match was rejected by the threshold or the
        left-right check; for ``"sgm"``: the ZNCC evaluated at the SGM disparity); NaN where
        it could not be computed (no-data, no texture, image border).
    vertical : ndarray (H, W), float32 or None
        Vertical offset ``v`` in pixels (``left(x, y) ~ right(x - d, y - v)``) when
        ``vertical_search > 0``, NaN where ``disparity`` is NaN; otherwise None.
    info : dict
        Matcher, options and the sub-pixel method, for reports.
    """

    disparity: np.ndarray
    score: np.ndarray
    vertical: np.ndarray | None = None
    info: dict = {}


# ----------------------------------------------------------------------------- helpers


def _as_image(a, name):
    return _image_and_finite(a, name)[0]


def _image_and_finite(a, name, mean=False):
    """``a`` as a float32 2-D image (checked: some pixel is finite), whether all its pixels
    are (one scan), and, with ``mean=True``, ``np.mean(a)`` where it proves the image finite
    (else None).

    ``mean=True`` (a caller that needs the image's mean: the score layer's centring constant,
    :func:`_zncc_left`): the float32 mean of a C-contiguous image is taken first, and a finite
    one replaces the scan (a float32 sum with a NaN or an infinity among its terms is not
    finite); a NaN or an overflow falls back to the scan."""
    a = np.asarray(a)
    if a.ndim != 2:
        raise InputError(f"{name}: expected a 2-D single-band image, got shape {a.shape}")
    a = a.astype(F32, copy=False)
    if mean and a.size and a.flags.c_contiguous:
        with np.errstate(over="ignore", invalid="ignore"):  # inf, NaN: the scan tells
            m = np.mean(a)
        if np.isfinite(m):
            return a, True, m
    fin = np.isfinite(a)
    finite = bool(fin.all())
    if not finite and not fin.any():
        raise InputError(f"{name}: image has no valid (finite) pixel")
    return a, finite, None


def _finite_sample(arrays, n, finite=False):
    """The finite values of ``arrays`` (concatenated, flattened) taken every ``size // n``-th
    when there are more than ``n``; without NaN the stride is taken without the copy.
    ``finite=True``: the caller knows the arrays have no NaN (their scan is skipped)."""
    flats = [np.ravel(a) for a in arrays]
    fin = None if finite else [np.isfinite(f) for f in flats]
    if finite or all(m.all() for m in fin):
        size = sum(f.size for f in flats)
        step = size // n if size > n else 1
        parts, start = [], 0
        for f in flats:  # v[::step] of the concatenation, piece by piece
            parts.append(f[start::step])
            start = (start - f.size) % step
        return np.concatenate(parts) if len(parts) > 1 else parts[0]
    v = np.concatenate([f[m] for f, m in zip(flats, fin)])
    return v[:: v.size // n] if v.size > n else v


def _robust_range(a):
    v = _finite_sample([a], 200_000)
    lo, hi = _percentiles(v, (2.0, 98.0))
    return float(lo), float(hi)


def _percentiles(v, q, step=64):
    """``np.percentile(v, q)`` (linear method) of a 1-D array of finite values, bit for bit,
    without NumPy's partition of the whole sample around six ranks.

    The two order statistics each percentile interpolates between are found among the values
    lying between two bounds taken from a sorted 1-in-``step`` sub-sample (a few comparison
    passes and a sort of a small set; a rank near either end of the sample, as the 1 and 99 %
    of the stretch, needs one bound only: all the values up to it, or from it, one comparison
    pass); the counts below the bounds check that the wanted ranks lie inside (else:
    ``np.percentile`` itself).  The interpolation is NumPy's own formula
    (``_lerp``: float32 differences, float64 weights, the ``>= 0.5`` branch)."""
    v = np.asarray(v)
    q = np.asarray(q, dtype=np.float64)
    n = v.size
    if v.ndim != 1 or n < 16 * step or not ((q > 0) & (q < 100)).all():
        return np.percentile(v, q)
    vi = (n - 1) * np.true_divide(q, 100)
    prev = np.floor(vi)
    gamma = vi - prev
    ranks = prev.astype(np.intp)
    sub = np.sort(v[::step])
    a = np.empty(q.shape, v.dtype)
    b = np.empty(q.shape, v.dtype)
    for i, r in enumerate(ranks):
        j = r // step  # about where rank r falls in the sub-sample
        m = 16 + 4 * int(math.sqrt(min(j, sub.size - j) + 1))  # ~4 sigma of the rank's spread
        lo_i, hi_i = j - m, j + 1 + m
        sel = None
        below = 0
        near = 3 * (2 * m + 1)  # a rank this near an end: one bound, one comparison pass
        if hi_i < sub.size and (lo_i <= 0 or hi_i <= near):
            sel = v <= sub[hi_i]  # all the values up to the upper bound (a tail: few)
        elif lo_i > 0 and (hi_i >= sub.size or sub.size - lo_i <= near):
            sel = v >= sub[lo_i]  # all the values from the lower bound up
            below = n - int(np.count_nonzero(sel))
        elif hi_i < sub.size:  # both bounds
            t = sub[lo_i]
            low = v < t
            below = int(np.count_nonzero(low))
            sel = (v <= sub[hi_i]) & ~low
        cand = v[sel] if sel is not None else v
        if not (below <= r and r + 1 < below + cand.size):
            return np.percentile(v, q)
        cand.partition((r - below, r + 1 - below))
        a[i], b[i] = cand[r - below], cand[r + 1 - below]
    return numpy_lerp(a, b, gamma)


@functools.lru_cache(maxsize=16)
def _box_kernels(window: int) -> tuple[np.ndarray, np.ndarray]:
    """The separable kernels of :func:`_box_mean`: ones along rows, ``1 / window**2`` along
    columns (float32, read-only, cached)."""
    ones = np.ones(window, F32)
    scaled = np.full(window, F32(1.0 / (window * window)), F32)
    ones.flags.writeable = scaled.flags.writeable = False
    return ones, scaled


def _box_mean(src, window: int, dst=None) -> np.ndarray:
    """Mean of each ``window`` x ``window`` window of a float32 image (zero outside it), as
    ``cv2.sepFilter2D`` (a float32 sum of ``window`` values along the row, then of ``window``
    row sums times ``1 / window**2``): the same windows as ``cv2.boxFilter(normalize=True,
    BORDER_CONSTANT)`` within float32 rounding (a few ulps), 1.6 times as fast on a 7 x 7
    window at 1 thread (OpenCV's float box filter accumulates running sums in float64).
    Each output depends only on its window, so bands with a halo give the same bits."""
    kx, ky = _box_kernels(int(window))
    return cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, dst=dst, borderType=cv2.BORDER_CONSTANT)


class _Stats(NamedTuple):
    zero: np.ndarray  # image with NaN -> 0
    mean: np.ndarray  # window mean
    inv: np.ndarray  # 1 / window std (or the std itself: see _window_stats); NaN where invalid


def _window_stats(img, window, min_std, finite=False, outside=(), inverse=True):
    """Window mean and inverse standard deviation of a float32 image with NaN no-data.

    ``inv`` is NaN where the window touches no-data or its standard deviation is below
    ``min_std``; the image border (windows leaving the image) is NaN as well. ``zero`` is
    ``img`` itself when it has no NaN (read-only use). The arithmetic is done in place
    (same operations, same float32 results as the textbook form ``1 / sqrt(E[x^2] - E[x]^2)``,
    the variance floored at 1e-30); the window means are :func:`_box_mean`'s.
    ``finite=True``: the caller knows ``img`` has no NaN (its scan is skipped).
    ``outside``: ``(columns, mask)`` pairs, more windows to invalidate (``mask`` is a boolean
    array of the shape of ``inv[:, columns]``), e.g. windows touching no-data the caller
    replaced by 0 and located itself.
    ``inverse=False``: the third field holds the standard deviation ``sqrt(E[x^2] - E[x]^2)``
    itself (not floored; NaN where invalid), for a caller that divides once by a product of
    two of them (:func:`_zncc_warped`).

    Windows below ``min_std`` or touching no-data get a NaN variance before the square root
    (NaN propagates through the square root, the floor and the division; with
    ``min_std == 0`` a negative variance, from rounding, needs no mask at all: its square root
    is NaN already); the image border and ``outside`` are set to NaN in ``inv`` afterwards.
    """
    img = np.asarray(img, dtype=F32)
    if finite:
        nan, has_nan = None, False
    else:
        nan = ~np.isfinite(img)
        has_nan = bool(nan.any())
    if has_nan:  # NaN -> 0 (a copy and a masked fill: a third of np.where)
        zero = img.copy()
        np.copyto(zero, F32(0), where=nan)
    else:
        zero = img
    mean = _box_mean(zero, window)
    tmp = np.multiply(zero, zero)
    var = _box_mean(tmp, window)
    near = None
    if has_nan:  # a NaN in the window: a dilation of the NaN mask (outside = 0)
        near = square_dilation(nan, window)
    floor = F32(min_std) ** 2 if min_std != 0 else None
    # 1 / sqrt(max(var, 1e-30)) == 1 / max(sqrt(var), sqrt(1e-30)) bit for bit (the rounded
    # square root is monotone), and the second form keeps NaN (negative variances included)
    with np.errstate(divide="ignore", invalid="ignore"):
        for rows in _row_bands(var.shape):  # element-wise, by bands that stay in cache
            v, t = var[rows], tmp[rows]
            np.multiply(mean[rows], mean[rows], out=t)
            np.subtract(v, t, out=v)  # E[x^2] - E[x]^2
            if floor is not None:
                np.copyto(v, F32(np.nan), where=v < floor)
            if near is not None:
                np.copyto(v, F32(np.nan), where=near[rows])
            cv2.sqrt(v, dst=v)  # IEEE, as np.sqrt (NaN below 0), twice as fast
            if inverse:
                np.maximum(v, _floor_row(_SQRT_TINY, v.shape[1]), out=v)
                np.divide(F32(1), v, out=v)
    inv = var
    for cols, mask in outside:
        inv[:, cols][mask] = np.nan
    h = window // 2
    inv[:h] = np.nan
    inv[-h:] = np.nan
    inv[:, :h] = np.nan
    inv[:, -h:] = np.nan
    return _Stats(zero, mean, inv)


def _row_bands(shape, nbytes=1 << 19):
    """Row slices of an image of ``shape`` covering it in bands of about ``nbytes`` bytes of
    float32 each (512 KiB: the few arrays of a band mostly stay in a core's 2 MiB cache
    between element-wise passes, and the calls per pass stay few; 256 KiB measured 0.75 ms
    slower on the 1024 x 1024 score layer)."""
    step = max(1, nbytes // (4 * max(shape[1], 1)))
    return [slice(r, r + step) for r in range(0, shape[0], step)]


def _gather_cols(a, cols, fill=np.nan):
    """``a[y, cols[y, x]]`` with out-of-range columns set to ``fill``."""
    h, w = a.shape
    ok = (cols >= 0) & (cols < w)
    c = np.clip(cols, 0, w - 1)
    out = np.take_along_axis(a, c, axis=1)
    if not ok.all():
        out = np.where(ok, out, fill).astype(a.dtype, copy=False)
    return out


def _warp_cols(a, seed):
    """``a(x - seed(x, y), y)`` by bicubic interpolation; NaN outside ``a`` and where the
    4x4 support touches no-data."""
    h, w = a.shape
    map_x = (np.arange(w, dtype=F32)[None, :] - seed).astype(F32)
    map_y = np.broadcast_to(np.arange(h, dtype=F32)[:, None], (h, w))
    nan = ~np.isfinite(a)
    src = np.where(nan, F32(0), a) if nan.any() else a
    out = cv2.remap(
        src,
        map_x,
        np.ascontiguousarray(map_y),
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    if nan.any():
        bad = cv2.remap(
            nan.astype(F32),
            map_x,
            np.ascontiguousarray(map_y),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=1.0,
        )
        out[square_dilation(bad > 0, 3)] = np.nan
    # outside the image
    out[(map_x < 0) | (map_x > w - 1)] = np.nan
    return out


def _shift_rows(a, dy):
    """``out[y] = a[y - dy]`` with NaN rows entering."""
    if dy == 0:
        return a
    out = np.full_like(a, np.nan)
    if dy > 0:
        out[dy:] = a[:-dy]
    else:
        out[:dy] = a[-dy:]
    return out


def _subpixel(c0, cm, cp, method):
    """Offset of the correlation peak from the integer maximum (in [-0.5, 0.5]).

    ``cm``/``cp`` are the scores at ``k - 1`` / ``k + 1``; NaN where they are missing or
    where the integer maximum is not a peak (the true maximum lies outside the range).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        if method == "parabola":
            den = cm - 2 * c0 + cp
            delta = (cm - cp) / (2 * den)
            ok = den < 0
        elif method == "vfit":
            lo = np.minimum(cm, cp)
            den = c0 - lo
            delta = (cp - cm) / (2 * den)
            ok = den > 0
        else:  # pragma: no cover - checked in match_rectified
            raise InputError(f"unknown subpixel method {method!r}")
    ok &= (c0 >= cm) & (c0 >= cp)
    delta = np.where(ok, np.clip(delta, -0.5, 0.5), np.nan)
    # a flat peak (both neighbours equal to the maximum) has no defined optimum
    return delta.astype(F32, copy=False)


class _Scan(NamedTuple):
    score: np.ndarray  # best ZNCC (-inf where none)
    k: np.ndarray  # offset of the best (int32)
    cm: np.ndarray  # ZNCC at k - 1
    cp: np.ndarray  # ZNCC at k + 1
    back_score: np.ndarray | None
    back_k: np.ndarray | None


def _scan(ref, tgt, klo, khi, window, min_std, back=False):
    """Stream ZNCC(ref(x), tgt(x - k)) over integer offsets ``klo..khi``.

    The scores at ``klo - 1`` and ``khi + 1`` are computed too, only as neighbours for the
    sub-pixel fit.  With ``back``, also tracks for every ``tgt`` pixel the best offset of the
    ``ref`` pixel matching it (the "right" disparity map, free for a full search).
    Memory: a dozen image-sized float32 arrays whatever the number of offsets.
    """
    h, w = ref.zero.shape
    pl = max(khi + 1, 0)
    pr = max(1 - klo, 0)
    padded = np.full((h, w + pl + pr), np.nan, dtype=F32)
    padded[:, pl : pl + w] = tgt
    t = _window_stats(padded, window, min_std)
    # columns of tgt's border are not windows leaving tgt: re-validate them by the NaN pad
    r = ref

    best = np.full((h, w), -np.inf, dtype=F32)
    bk = np.full((h, w), klo - 1, dtype=np.int32)
    cm = np.full((h, w), np.nan, dtype=F32)
    cp = np.full((h, w), np.nan, dtype=F32)
    if back:
        bbest = np.full((h, w), -np.inf, dtype=F32)
        bbk = np.full((h, w), klo - 1, dtype=np.int32)
        bupd = np.empty((h, w), dtype=bool)
    prod = np.empty((h, w), dtype=F32)
    boxed = np.empty((h, w), dtype=F32)
    tmp = np.empty((h, w), dtype=F32)
    c = np.empty((h, w), dtype=F32)
    cprev = np.full((h, w), np.nan, dtype=F32)
    upd = np.empty((h, w), dtype=bool)
    upd_prev = np.zeros((h, w), dtype=bool)
    have_prev = False
    for k in range(klo - 1, khi + 2):
        sl = slice(pl - k, pl - k + w)
        cv2.multiply(r.zero, t.zero[:, sl], dst=prod)
        _box_mean(prod, window, dst=boxed)
        np.multiply(r.mean, t.mean[:, sl], out=tmp)
        np.subtract(boxed, tmp, out=c)
        np.multiply(c, r.inv, out=c)
        np.multiply(c, t.inv[:, sl], out=c)
        if have_prev:
            np.copyto(cp, c, where=upd_prev)
        if klo <= k <= khi:
            np.greater(c, best, out=upd)
            np.copyto(best, c, where=upd)
            np.copyto(bk, k, where=upd)
            np.copyto(cm, cprev, where=upd)
            upd, upd_prev = upd_prev, upd
            have_prev = True
            if back and abs(k) < w:
                # tgt pixel xt = x - k is matched by ref pixel x = xt + k (at |k| >= w no
                # pixel has a partner inside the other image)
                if k >= 0:
                    cs, bs = c[:, k:], np.s_[:, : w - k]
                else:
                    cs, bs = c[:, : w + k], np.s_[:, -k:]
                bb = bbest[bs]
                m = bupd[bs]
                np.greater(cs, bb, out=m)
                np.copyto(bb, cs, where=m)
                np.copyto(bbk[bs], k, where=m)
        else:
            have_prev = False
        c, cprev = cprev, c
    # cp of a maximum found at the very last offset was filled at khi + 1
    return _Scan(best, bk, cm, cp, bbest if back else None, bbk if back else None)


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


def _seed_columns(d, w, holes=None):
    """The score layer's warp: ``x - np.rint(_fill_seed(d, 0.0))`` as float32 (the remap's
    column map, whole pixels), in one pass from the uint8 median when the seed's span allows
    (integers: exact either way), and the rounded seed's min and max (pixels: the map lies in
    ``x - max .. x - min``).  ``holes``: :func:`_rounded_filled`'s."""
    r, lo, hi = _rounded_filled(d, holes)
    base, med = _median_offset(r, lo, hi)
    m = med.astype(F32, copy=False)  # a fresh array either way: the map is built in it
    return np.subtract(np.subtract(_col_index(w), F32(base)), m, out=m), lo, hi


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


def _lr_check(d_left, d_right, tol):
    """Mask of left pixels whose disparity agrees with the right map within ``tol`` px."""
    h, w = d_left.shape
    cols = np.arange(w, dtype=F32)[None, :]
    with np.errstate(invalid="ignore"):
        xr = np.rint(cols - d_left)
        xr = np.where(np.isfinite(xr), xr, -1).astype(np.int64)
        back = _gather_cols(d_right, xr)
        return np.abs(d_left - back) <= tol


def _match_pass(ref, tgt, seed, klo, khi, window, min_std, subpixel, vertical, back=False):
    """One ZNCC pass: ``ref(x, y)`` against ``tgt`` warped by a seed and shifted by ``k``.

    ``seed`` is a float seed disparity map ``S`` (None: a plain full search over
    ``klo..khi``): ``tgt`` is first warped (bicubic) to ``tgt'(x) = tgt(x - S(x), y - dy)``,
    then ``ref(x)`` is correlated with ``tgt'(x - k)``, so the window follows the seed
    surface and the disparity is ``k + S(x - k)`` plus the sub-pixel offset.  Returns disparity
    (float, NaN where no peak), score, vertical offset, and (with ``back``) the integer disparity
    map of ``tgt`` seen from ``tgt`` (full search only).
    """
    h, w = ref.shape
    rstats = _window_stats(ref, window, min_std)
    cols = np.arange(w, dtype=np.int64)[None, :]
    best = None
    per_dy = []
    for dy in range(-vertical, vertical + 1):
        t = _shift_rows(tgt, dy)
        if seed is not None:
            t = _warp_cols(t, seed)
        s = _scan(rstats, t, klo, khi, window, min_std, back=back and dy == 0)
        per_dy.append(s.score)
        if best is None:
            best, best_dy = s, np.full((h, w), dy, dtype=np.int32)
            back_res = (s.back_score, s.back_k)
            continue
        better = s.score > best.score
        best = _Scan(
            *(
                np.where(better, new, old) if new is not None else old
                for new, old in zip(s[:4], best[:4])
            ),
            None,
            None,
        )
        best_dy[better] = dy
    score = best.score
    found = np.isfinite(score)
    delta = _subpixel(score, best.cm, best.cp, subpixel)
    k = best.k
    if seed is not None:
        base = _gather_cols(seed, cols - k, fill=np.nan)
    else:
        base = 0
    disp = (k + base + delta).astype(F32)
    disp[~found] = np.nan
    score = np.where(found, score, np.nan).astype(F32)
    vert = None
    if vertical:
        stack = np.stack(per_dy)  # (2v+1, H, W)
        i = best_dy + vertical
        vm = np.take_along_axis(stack, np.clip(i - 1, 0, 2 * vertical)[None], 0)[0]
        vp = np.take_along_axis(stack, np.clip(i + 1, 0, 2 * vertical)[None], 0)[0]
        vm = np.where(i - 1 >= 0, vm, np.nan)
        vp = np.where(i + 1 <= 2 * vertical, vp, np.nan)
        dv = _subpixel(best.score, vm, vp, "parabola")
        # the edge of the vertical range keeps the integer offset
        vert = (best_dy + np.where(np.isfinite(dv), dv, 0)).astype(F32)
        vert[np.isnan(disp)] = np.nan
    back_disp = None
    if back and back_res[0] is not None:
        bs, bk = back_res
        back_disp = np.where(np.isfinite(bs), bk, np.nan).astype(F32)
    return disp, score, vert, back_disp


def _auto_levels(lo, hi, shape):
    levels = 0
    span = hi - lo
    while span / 2**levels > 24 and min(shape) / 2 ** (levels + 1) >= 48 and levels < 6:
        levels += 1
    return levels


def _forward_seed(seed_left, w):
    """Right-image seed from a left-image seed by forward projection (foreground wins)."""
    h = seed_left.shape[0]
    xr = np.rint(np.arange(w)[None, :] - seed_left).astype(np.int64)
    ok = np.isfinite(seed_left) & (xr >= 0) & (xr < w)
    out = np.full(h * w, -np.inf, dtype=F32)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    np.maximum.at(out, (rows[ok] * w + xr[ok]), seed_left[ok])
    out = out.reshape(h, w)
    out[~np.isfinite(out)] = np.nan
    return out


# ----------------------------------------------------------------------------- ncc


def _match_ncc(
    left,
    right,
    lo,
    hi,
    range_maps,
    *,
    window,
    min_score,
    min_std,
    lr_tolerance,
    subpixel,
    levels,
    margin,
    vertical_search,
):
    h, w = left.shape
    flip = np.s_[:, ::-1]

    def both_ways(L, R, seedL, seedR, klo, khi, vert):
        """Left and right disparity maps at one level (right by flipping the pair)."""
        if seedL is None:
            dL, sL, vL, dR = _match_pass(
                L, R, None, klo, khi, window, min_std, subpixel, vert, back=vert == 0
            )
            if dR is None:  # with vertical search the back map is computed separately
                dRf, _, _, _ = _match_pass(
                    R[flip], L[flip], None, klo, khi, window, min_std, subpixel, vert
                )
                dR = dRf[flip]
            return dL, sL, vL, dR
        outs = []
        for ref, tgt, seed in ((L, R, seedL), (R[flip], L[flip], seedR[flip])):
            outs.append(
                _match_pass(
                    ref,
                    tgt,
                    np.ascontiguousarray(seed, dtype=F32),
                    klo,
                    khi,
                    window,
                    min_std,
                    subpixel,
                    vert,
                )
            )
        (dL, sL, vL, _), (dRf, _, _, _) = outs
        return dL, sL, vL, np.ascontiguousarray(dRf[flip])

    if range_maps is not None:
        dmin_map, dmax_map = range_maps
        seedL = (0.5 * (dmin_map + dmax_map)).astype(F32)
        half = 0.5 * (dmax_map - dmin_map)
        m = int(math.ceil(np.nanmax(half)))
        mid = float(np.nanmedian(seedL))
        seedR = _fill_seed(_forward_seed(seedL, w), mid)
        seedL = _fill_seed(seedL, mid)
        dL, sL, vL, dR = both_ways(left, right, seedL, seedR, -m, m, vertical_search)
        levels = 0
    else:
        if levels is None:
            levels = _auto_levels(lo, hi, left.shape)
        pl = build_pyramid(left, levels)
        pr = build_pyramid(right, levels)
        f = 2**levels
        clo, chi = math.floor(lo / f), math.ceil(hi / f)
        seedL = seedR = None
        # the coarse levels' seeds are always left-right checked (at least 1 px); the caller's
        # lr_tolerance (None: no check) applies to the result
        seed_tol = 1.0 if lr_tolerance is None else max(lr_tolerance, 1.0)
        for lev in range(levels, -1, -1):
            L, R = pl[lev], pr[lev]
            vert = math.ceil(vertical_search / 2**lev)
            if seedL is None:
                dL, sL, vL, dR = both_ways(L, R, None, None, clo, chi, vert)
            else:
                seedL = upsample_field(seedL, L.shape)
                seedR = upsample_field(seedR, L.shape)
                dL, sL, vL, dR = both_ways(L, R, seedL, seedR, -margin, margin, vert)
            if lev > 0:
                okL = _lr_check(dL, dR, seed_tol)
                okR = _lr_check(dR[flip], dL[flip], seed_tol)[flip]
                fb = 0.5 * (lo + hi) / 2**lev
                seedL = _fill_seed(np.where(okL & (sL >= min(min_score, 0.3)), dL, np.nan), fb)
                seedR = _fill_seed(np.where(okR, dR, np.nan), fb)
    valid = np.isfinite(dL)
    if lr_tolerance is not None:
        valid &= _lr_check(dL, dR, lr_tolerance)
    if min_score is not None:
        with np.errstate(invalid="ignore"):
            valid &= sL >= min_score
    if range_maps is not None:
        with np.errstate(invalid="ignore"):
            valid &= (dL >= range_maps[0] - 0.5) & (dL <= range_maps[1] + 0.5)
    else:
        with np.errstate(invalid="ignore"):
            valid &= (dL >= lo - 0.5) & (dL <= hi + 0.5)
    disp = np.where(valid, dL, np.nan).astype(F32)
    vert = None
    if vertical_search:
        vert = np.where(valid, vL, np.nan).astype(F32)
    return disp, sL.astype(F32), vert, {"levels": levels}


# ----------------------------------------------------------------------------- sgm


def _to_uint8(left, right, finite=(False, False)):
    """Joint 1-99 % percentile stretch of both images to uint8 (NaN -> 0).

    ``round-half-up((a - lo) * 255 / (hi - lo))`` clipped to 0..255, in float64
    (:func:`stereodem.core.stretch.linear_to_uint8`).
    ``finite``: for each image, whether the caller knows it has no NaN (scans skipped)."""
    v = _finite_sample([left, right], 400_000, finite=all(finite))
    lo, hi = _percentiles(v, (1.0, 99.0))
    scale = 255.0 / max(hi - lo, 1e-12)

    def conv(a, finite):
        b = linear_to_uint8(a, lo, scale)
        nan = None if finite else np.isnan(a)
        # no-data takes the value of ``lo`` (as float32, like the image)
        if nan is not None and nan.any():
            b[nan] = np.uint8(np.clip((a.dtype.type(lo) - lo) * scale + 0.5, 0, 255))
        return b

    return conv(left, finite[0]), conv(right, finite[1])


_SGBM_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}
#: ``sgm_mode`` and ``subpixel`` choices of :func:`match_rectified`
SGM_MODES: tuple[str, ...] = tuple(_SGBM_MODES)
SUBPIXELS: tuple[str, ...] = ("parabola", "vfit")


def _sgbm(
    left8,
    right8,
    lo,
    hi,
    *,
    block_size=5,
    p1=None,
    p2=None,
    lr_tolerance=1,
    uniqueness=10,
    speckle_window=100,
    speckle_range=2,
    pre_filter_cap=63,
    mode="sgbm",
):
    """Run ``cv2.StereoSGBM`` on uint8 images for ``lo..hi``; float32 disparity, NaN invalid.

    OpenCV leaves the columns ``x < minDisparity + numDisparities`` and
    ``x >= width + min(minDisparity, 0)`` invalid, so the pair is padded on each side (edge
    replication) by what it takes for every column that can have a match to be matched, and
    the padding is cropped from the result (:func:`_sgbm_padding`; more on the left where
    OpenCV needs a wider pair; no call at all where no column can match). A disparity whose match
    ``x - d`` falls outside the right image (onto the padding) is no measurement: it is NaN,
    and so is one beyond ``hi + 0.5`` (OpenCV searches ``numDisparities`` rounded up to a
    multiple of 16).
    """
    nd = int(math.ceil((hi - lo + 1) / 16.0)) * 16
    h, w = left8.shape
    if max(lo, 0) >= w + min(hi, 0):  # no column can have a match in lo..hi
        return np.full((h, w), np.nan, F32)
    padl, padr = _sgbm_padding(lo, hi, nd)
    # OpenCV refuses a pair not wider than minDisparity + numDisparities + blockSize // 2
    # (a tile with few columns that can match): more padding on the left, cropped as well
    padl += max(lo + nd + block_size // 2 + 1 - (w + padl + padr), 0)
    if padl or padr:
        left8 = cv2.copyMakeBorder(left8, 0, 0, padl, padr, cv2.BORDER_REPLICATE)
        right8 = cv2.copyMakeBorder(right8, 0, 0, padl, padr, cv2.BORDER_REPLICATE)
    b2 = block_size * block_size
    sgbm = cv2.StereoSGBM_create(
        minDisparity=int(lo),
        numDisparities=nd,
        blockSize=block_size,
        P1=int(p1 if p1 is not None else 8 * b2),
        P2=int(p2 if p2 is not None else 32 * b2),
        disp12MaxDiff=-1 if lr_tolerance is None else int(max(1, round(lr_tolerance))),
        preFilterCap=pre_filter_cap,
        uniquenessRatio=uniqueness,
        speckleWindowSize=speckle_window,
        speckleRange=speckle_range,
        mode=_SGBM_MODES[mode],
    )
    raw = sgbm.compute(left8, right8)
    raw = raw[:, padl : raw.shape[1] - padr]
    disp = np.divide(raw, F32(16.0), dtype=F32)
    if lo + nd - 1 > hi:
        # OpenCV searched lo .. lo + nd - 1 (nd rounded up to 16): a disparity beyond the
        # requested hi by more than half a pixel (the per-pixel range maps' tolerance) lies
        # outside the range the caller asked for
        disp[(raw < lo * 16) | (raw > hi * 16 + 8)] = np.nan
    else:
        disp[raw < lo * 16] = np.nan  # few cells: an index is cheaper than a masked copy
    # matches onto the padding: x - d < -0.5 (d > x + 0.5) in the first columns, or
    # x - d > w - 0.5 in the last ones (d < x - w + 0.5); only the strips where that can
    # happen are looked at
    a = min(max(lo + nd + 1, 0), w)  # d < lo + nd: x - d > -0.5 from x = lo + nd on
    if a > 0:
        left = disp[:, :a]
        with np.errstate(invalid="ignore"):
            left[left > _col_index(w)[:, :a] + F32(0.5)] = np.nan
    b = max(w + min(lo, 0) - 1, 0)  # d >= lo: x - d < w - 0.5 below x = w + lo
    if b < w:
        right = disp[:, b:]
        with np.errstate(invalid="ignore"):
            right[right < _col_index(w)[:, b:] - F32(w - 0.5)] = np.nan
    return disp


def _sgbm_padding(lo: int, hi: int, nd: int) -> tuple[int, int]:
    """Columns of edge padding (left, right) for ``cv2.StereoSGBM`` to match every column of
    a tile that can have a match in ``lo..hi`` (``nd``: the rounded ``numDisparities``).

    A left column ``x`` can have a match only if ``0 <= x - d < width`` for some ``d`` in
    ``lo..hi``: ``x >= max(lo, 0)`` and ``x < width + min(hi, 0)``. OpenCV computes the
    columns ``lo + nd <= x' < width' + min(lo, 0)`` of the padded pair (``x' = x + left``,
    ``width' = width + left + right``), hence ``left = lo + nd - max(lo, 0)`` and
    ``right = min(hi, 0) - min(lo, 0)`` (at least 0); columns that cannot have a match get
    no padding (a one-sided range of ``lo > 0`` saves ``lo`` columns, one of ``hi < 0``
    saves ``-hi``)."""
    return max(lo + nd - max(lo, 0), 0), max(min(hi, 0) - min(lo, 0), 0)


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


@functools.lru_cache(maxsize=8)
def _col_index(w):
    """Column coordinates ``0..w-1`` as a (1, w) float32 row (read-only, cached)."""
    a = np.arange(w, dtype=F32)[None, :]
    a.flags.writeable = False
    return a


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
        np.subtract(warped, level_r, out=warped, dtype=F32)
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


@functools.lru_cache(maxsize=8)
def _floor_row(value: float, w: int):
    """``value`` as a (1, w) float32 row (read-only, cached): ``np.maximum`` against a row
    takes NumPy's vectorised loop, against a scalar a loop 2-3 times as slow (the floors
    :data:`_TINY` and :data:`_SQRT_TINY`)."""
    a = np.full((1, w), value, F32)
    a.flags.writeable = False
    return a


def _nan_border(a, h):
    """Set the ``h`` first and last rows and columns of ``a`` to NaN (in place): the cells
    whose ``2 h + 1`` window leaves the image."""
    if h:
        a[:h] = np.nan
        a[-h:] = np.nan
        a[:, :h] = np.nan
        a[:, -h:] = np.nan


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
    buf = np.multiply(warped, warped)
    var_r = _box_mean(buf, window)
    mean_l = _box_mean(z, window)
    np.multiply(z, z, out=buf)
    var_l = _box_mean(buf, window)
    np.multiply(z, warped, out=buf)
    cov = _box_mean(buf, window)
    t, mr, ml = buf[keep], mean_r[keep], mean_l[keep]
    vr, vl, c = var_r[keep], var_l[keep], cov[keep]
    with np.errstate(invalid="ignore", divide="ignore"):
        np.multiply(mr, mr, out=t)
        np.subtract(vr, t, out=vr)  # E[r^2] - E[r]^2
        cv2.sqrt(vr, dst=vr)  # NaN where negative (rounding), as np.sqrt
        np.multiply(ml, ml, out=t)
        np.subtract(vl, t, out=vl)
        cv2.sqrt(vl, dst=vl)
        np.multiply(ml, mr, out=t)
        np.subtract(c, t, out=c)  # E[lr] - E[l] E[r]
        np.multiply(vr, vl, out=vr)
        np.maximum(vr, _floor_row(_TINY, vr.shape[1]), out=vr)
        np.divide(c, vr, out=c)
        np.clip(c, -1, 1, out=out)


# ----------------------------------------------------------------------------- public


def match_rectified(
    left,
    right,
    disp_range,
    matcher="ncc",
    *,
    window: int | None = None,
    min_score: float | None = None,
    min_std: float | None = None,
    lr_tolerance: float | None = 1.0,
    subpixel: str = "parabola",
    levels: int | None = None,
    margin: int = 2,
    vertical_search: int = 0,
    sgm_mode: str = "sgbm",
    sgm_p1: int | None = None,
    sgm_p2: int | None = None,
    sgm_uniqueness: int = 10,
    sgm_speckle_window: int = 100,
    sgm_speckle_range: int = 2,
):
    """Dense disparity of a rectified pair (rows correspond).

    Parameters
    ----------
    left, right : ndarray (H, W)
        Epipolar images (any real dtype, converted to float32); NaN marks no-data.
    disp_range : (dmin, dmax) or (dmin_map, dmax_map)
        Inclusive disparity search range in pixels (``left(x) ~ right(x - d)``): two numbers,
        or two (H, W) arrays giving a per-pixel range, e.g. from a seed DEM or a coarse
        disparity map +/- a margin (``(seed - m, seed + m)``).  With maps, ``"ncc"`` warps
        the right image by the mid-range map and searches +/- the largest half-width, then
        rejects peaks outside each pixel's own range; ``"sgm"`` searches the overall min..max
        and rejects results outside each pixel's range.
    matcher : {"ncc", "sgm"}
    window : int, optional
        Odd window side in pixels: ZNCC window (default 7) or SGBM ``blockSize`` (default 5).
    min_score : float, optional
        Minimum ZNCC of a valid match; default 0.5 for ``"ncc"``, none for ``"sgm"``.
    min_std : float, optional
        Texture mask: windows whose standard deviation (image units) is below this get no
        match; default 1 % of the left image's 2-98 % percentile range.  ``"ncc"`` only
        (``"sgm"`` has OpenCV's uniqueness and speckle filters instead).
    lr_tolerance : float or None
        Left-right consistency tolerance in pixels (default 1); None disables the check.
        For ``"sgm"`` it is OpenCV's ``disp12MaxDiff`` (rounded, at least 1).
    subpixel : {"parabola", "vfit"}
        ``"ncc"`` sub-pixel refinement: parabola through the peak and its neighbours, or the
        symmetric (equiangular) V fit.  A peak at the edge of the range is rejected.
    levels : int, optional
        ``"ncc"`` pyramid levels above full resolution; default: halve until the range is
        at most 24 px (and the image at least 96 px); 0 = single-scale full search.
    margin : int
        ``"ncc"`` search half-width (pixels) around the upsampled coarse disparity at each
        finer level (default 2).
    vertical_search : int
        ``"ncc"`` only: also search row offsets ``-v..v`` (residual vertical parallax, e.g.
        ASTER jitter) and return the sub-pixel vertical offset in ``.vertical``.
    sgm_mode : {"sgbm", "3way", "hh", "hh4"}
        OpenCV SGBM mode (default ``"sgbm"``, 5 paths one pass).
    sgm_p1, sgm_p2, sgm_uniqueness, sgm_speckle_window, sgm_speckle_range
        SGBM smoothness penalties (default 8 and 32 x window^2), uniqueness ratio (%),
        speckle filter size (px) and range (px).

    Returns
    -------
    MatchResult
        ``disparity`` (float32, NaN invalid; never a match outside the right image),
        ``score`` (float32 ZNCC), ``vertical`` (or None), ``info``.

    Raises
    ------
    InputError
        Shapes differ, images are not 2-D or all no-data, the range is empty, or an option
        is out of its domain.
    """
    # the sgm score layer centres by the left image's mean: taken first, it spares the scan
    left, left_finite, left_mean = _image_and_finite(left, "left", mean=matcher == "sgm")
    right, right_finite, _ = _image_and_finite(right, "right")
    if left.shape != right.shape:
        raise InputError(f"left/right: shapes differ, {left.shape} vs {right.shape}")
    if matcher not in MATCHERS:
        raise InputError(
            f"matcher: unknown {matcher!r}, expected {' or '.join(map(repr, MATCHERS))}"
        )
    if subpixel not in SUBPIXELS:
        raise InputError(f"subpixel: unknown {subpixel!r}, expected 'parabola' or 'vfit'")
    if window is None:
        window = 7 if matcher == "ncc" else 5
    if window < 3 or window % 2 == 0:
        raise InputError(f"window: must be odd and >= 3, got {window}")
    vertical_search = int(vertical_search)
    if vertical_search < 0:
        raise InputError(f"vertical_search: must be >= 0, got {vertical_search}")
    if matcher == "sgm" and vertical_search:
        raise InputError("vertical_search: only available with matcher='ncc'")
    if len(disp_range) != 2:
        raise InputError("disp_range: expected (dmin, dmax) or (dmin_map, dmax_map)")
    range_maps = None
    a, b = disp_range
    if np.ndim(a) == 0 and np.ndim(b) == 0:
        lo, hi = int(math.floor(a)), int(math.ceil(b))
    else:
        a = np.broadcast_to(np.asarray(a, dtype=F32), left.shape)
        b = np.broadcast_to(np.asarray(b, dtype=F32), left.shape)
        if not np.isfinite(a).any():
            raise InputError("disp_range: the per-pixel range maps have no finite value")
        range_maps = (a, b)
        lo, hi = int(math.floor(np.nanmin(a))), int(math.ceil(np.nanmax(b)))
    if hi < lo:
        raise InputError(f"disp_range: empty range ({disp_range[0]}, {disp_range[1]})")
    if min_std is None and matcher == "ncc":  # the texture mask is "ncc"'s only
        p2, p98 = _robust_range(left)
        min_std = 0.01 * (p98 - p2)
    info = {
        "matcher": matcher,
        "window": window,
        "disp_range": (lo, hi),
        "lr_tolerance": lr_tolerance,
        "min_std": None if min_std is None else float(min_std),
    }

    if matcher == "ncc":
        if min_score is None:
            min_score = 0.5
        # centring each image by a constant keeps ZNCC exact and float32 sums well
        # conditioned; each by its own, since the two may sit at different levels
        disp, score, vert, extra = _match_ncc(
            left - F32(np.nanmean(left)),
            right - F32(np.nanmean(right)),
            lo,
            hi,
            range_maps,
            window=window,
            min_score=min_score,
            min_std=min_std,
            lr_tolerance=lr_tolerance,
            subpixel=subpixel,
            levels=levels,
            margin=int(margin),
            vertical_search=vertical_search,
        )
        info.update(
            extra,
            subpixel=subpixel,
            min_score=min_score,
            margin=int(margin),
            vertical_search=vertical_search,
        )
        return MatchResult(disp, score, vert, info)

    score_window = max(window, 7)
    l8, r8 = _to_uint8(left, right, finite=(left_finite, right_finite))
    disp = _sgbm(
        l8,
        r8,
        lo,
        hi,
        block_size=window,
        p1=sgm_p1,
        p2=sgm_p2,
        lr_tolerance=lr_tolerance,
        uniqueness=sgm_uniqueness,
        speckle_window=sgm_speckle_window,
        speckle_range=sgm_speckle_range,
        mode=sgm_mode,
    )
    masks = None
    if not (left_finite and right_finite):
        k = (window, window)
        masks = tuple(
            cv2.boxFilter((~np.isfinite(a)).astype(F32), cv2.CV_32F, k, normalize=False) > 0.5
            for a in (left, right)
        )
    # the score's left windows come band by band with its warped part, on OpenCV's threads
    # (SGBM itself runs on one): computing them beside SGBM on a second thread, as before,
    # took as long on 2 cores and more CPU (bench_match.py: 1.136 vs 1.140 x the bare call's
    # wall, 1.17 vs 1.20 x its CPU)
    left_windows = _zncc_left(left, score_window, finite=left_finite, mean=left_mean)
    # no-data: the block around the left pixel or around its match touches NaN
    if masks is not None:
        bad_l, bad_r = masks
        with np.errstate(invalid="ignore"):
            xr = np.where(np.isfinite(disp), np.rint(np.arange(left.shape[1]) - disp), -1)
        bad = bad_l | (_gather_cols(bad_r.astype(F32), xr.astype(np.int64), fill=1) > 0.5)
        disp[bad] = np.nan
    # the score's bands on OpenCV's threads (SGBM itself runs on one)
    score = _zncc_warped(
        left_windows, right, disp, right_finite=right_finite, threads=cv2.getNumThreads()
    )
    if range_maps is not None:
        with np.errstate(invalid="ignore"):
            disp[~((disp >= range_maps[0] - 0.5) & (disp <= range_maps[1] + 0.5))] = np.nan
    if min_score is not None:
        with np.errstate(invalid="ignore"):
            disp[~(score >= min_score)] = np.nan
    info.update(sgm_mode=sgm_mode, min_score=min_score, score_window=max(window, 7))
    return MatchResult(disp, score, None, info)
