"""The matchers' float32 images: the input check, finite samples and their percentiles
(the 8-bit stretch's and the texture mask's ranges), column coordinates and gathers along
the rows (the epipolar lines)."""

from __future__ import annotations

import functools
import math

import numpy as np

from stereodem.core.blocks import numpy_lerp
from stereodem.core.errors import InputError

F32 = np.float32


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


def _gather_cols(a, cols, fill=np.nan):
    """``a[y, cols[y, x]]`` with out-of-range columns set to ``fill``."""
    h, w = a.shape
    ok = (cols >= 0) & (cols < w)
    c = np.clip(cols, 0, w - 1)
    out = np.take_along_axis(a, c, axis=1)
    if not ok.all():
        out = np.where(ok, out, fill).astype(a.dtype, copy=False)
    return out


@functools.lru_cache(maxsize=8)
def _col_index(w):
    """Column coordinates ``0..w-1`` as a (1, w) float32 row (read-only, cached)."""
    a = np.arange(w, dtype=F32)[None, :]
    a.flags.writeable = False
    return a
