"""Linear stretch of an image to 8 bits, the one implementation the matchers share.

``round-half-up((a - lo) * scale)`` clipped to 0..255, computed in float64 by bands of rows
through one 1 MiB buffer that stays in cache: the same bits as the whole-image float64
formula, without its full-size float64 temporaries (a 5000 × 5400 ASTER band would need
216 MB of them, paid in page faults on first touch).

A float32 image takes a faster road to the same bits (:func:`_float32_certified`): OpenCV's
float32 ``convertScaleAbs`` twice, with the offset moved down and up by a bound ``e`` of its
rounding error; where the two agree the float64 formula gives that value too, and the few
pixels where they differ (about ``2 e`` of them) are computed with the float64 formula.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

__all__ = ["linear_to_uint8"]

_BUFFER_BYTES = 1 << 20  # float64 rows per band: 1 MiB
_F32_ROWS_BYTES = 1 << 20  # float32 rows per band of the certified path (in L2 cache)
_U32 = 2.0**-24  # float32 unit roundoff
_MAX_E = 1.0 / 64  # beyond this error bound (|lo * scale| above ~4e4): the float64 road


def linear_to_uint8(a, lo, scale) -> np.ndarray:
    """``a`` (2-D, any real dtype) mapped to uint8 by ``(a - lo) * scale + 0.5`` in float64,
    clipped to 0..255 and truncated (round half up); NaN gives an unspecified value: the
    caller sets its own no-data value where it needs one.

    A float32 image goes through :func:`_float32_certified` when it applies (same bits, about
    half the time on a 1024² tile)."""
    a = np.asarray(a)
    b = np.empty(a.shape, np.uint8)
    if a.size == 0:
        return b
    if a.dtype == np.float32 and a.ndim == 2 and _float32_certified(a, lo, scale, b):
        return b
    step = max(1, (_BUFFER_BYTES // 8) // max(a.shape[1], 1))
    buf = np.empty((step, a.shape[1]), np.float64)
    for r in range(0, a.shape[0], step):
        n = min(step, a.shape[0] - r)
        _formula(a[r : r + n], lo, scale, buf[:n], b[r : r + n])
    return b


def _formula(src, lo, scale, buf, dst):
    """The float64 formula: ``dst[...] = clip((src - lo) * scale + 0.5, 0, 255)`` truncated,
    through ``buf`` (float64, ``src``'s shape)."""
    with np.errstate(invalid="ignore"):  # NaN: set by the caller
        # float64 stated: numpy 1 subtracts a float scalar from float32 in float32
        np.subtract(src, lo, out=buf, dtype=np.float64)
        np.multiply(buf, scale, out=buf)
        np.add(buf, 0.5, out=buf)
        np.clip(buf, 0, 255, out=buf)
        np.copyto(dst, buf, casting="unsafe")


@functools.lru_cache(maxsize=1)
def _opencv_rounds_float32() -> bool:
    """Whether ``cv2.convertScaleAbs`` of float32 values computes ``|x * alpha + beta|`` in
    float32 (or better) and rounds it to the nearest integer, saturated (what
    :func:`_float32_certified` relies on): checked once on values a few float32 ulps from
    the halves, tiled over a 32 x 320 image (OpenCV's vector loops and scalar tails)."""
    x = np.array(
        [0.4999, 0.5001, 1.4999, 1.5001, 254.4999, 254.5001, 255.49, 300.0, 77.0, -0.4999],
        np.float32,
    )
    want = np.array([0, 1, 1, 2, 254, 255, 255, 255, 77, 0], np.uint8)
    # 128 * (1 +- ulp) - 127.5: 0.5 +- 2^-16 and 2^-17, decided only in float32 precision
    y = np.array([1 + 2.0**-23, 1 - 2.0**-24], np.float32)
    try:
        got = cv2.convertScaleAbs(np.tile(x, (32, 32)), alpha=1.0, beta=0.0)
        near = cv2.convertScaleAbs(np.tile(y, (32, 160)), alpha=128.0, beta=-127.5)
    except cv2.error:
        return False
    ok = np.array_equal(got, np.tile(want, (32, 32)))
    return bool(ok and np.array_equal(near, np.tile(np.array([1, 0], np.uint8), (32, 160))))


def _float32_certified(a, lo, scale, out) -> bool:
    """:func:`linear_to_uint8` of a 2-D float32 image into ``out``, the same bits as the
    float64 formula; False (nothing written) where it does not apply.

    The formula is a non-decreasing function ``f`` of ``a``, 0 at ``L = float32(lo)`` and 255
    at ``U = float32(lo + 255 / scale)`` (checked), so clipping ``a`` to ``L..U`` changes
    nothing (NaN stays unspecified) and keeps ``z = (a - lo) * scale`` within ``-0.25..255.25``.
    There OpenCV's float32 ``|a * alpha + beta|``, rounded, is ``z - e`` and ``z + e``
    rounded to the nearest integer with ``beta = -lo * scale -+ e``: its error is below
    ``e / 2 = 2^-24 (3.1 |lo * scale| + 800)`` (three float32 roundings and the float32
    ``alpha`` and ``beta``, for ``|a * scale| <= |lo * scale| + 256``; the float64 formula's
    own error is far below), so where both give ``m``, ``z`` lies strictly within
    ``m +- 0.5`` and the formula gives ``m``; elsewhere it is computed as in float64."""
    lo_f, scale_f = float(lo), float(scale)
    if not (math.isfinite(lo_f) and math.isfinite(scale_f) and scale_f > 0):
        return False
    shift = lo_f * scale_f
    e = 2.0 * _U32 * (3.1 * abs(shift) + 800.0)
    if not e <= _MAX_E or not _opencv_rounds_float32():
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        lim = np.array([lo_f, lo_f + 255.0 / scale_f], np.float32)
    if not np.isfinite(lim).all():
        return False
    z = (lim.astype(np.float64) - lo_f) * scale_f
    ends = np.empty(2, np.uint8)
    _formula(lim, lo, scale, np.empty(2, np.float64), ends)
    if ends.tolist() != [0, 255] or not (abs(z[0]) <= 0.25 and abs(z[1] - 255.0) <= 0.25):
        return False
    h, w = a.shape
    step = max(1, (_F32_ROWS_BYTES // 4) // max(w, 1))
    clipped = np.empty((min(step, h), w), np.float32)
    other = np.empty((min(step, h), w), np.uint8)
    for r in range(0, h, step):
        n = min(step, h - r)
        c, o, dst = clipped[:n], other[:n], out[r : r + n]
        np.clip(a[r : r + n], lim[0], lim[1], out=c)
        cv2.convertScaleAbs(c, dst=dst, alpha=scale_f, beta=-shift - e)
        cv2.convertScaleAbs(c, dst=o, alpha=scale_f, beta=-shift + e)
        differ = np.flatnonzero(np.not_equal(dst, o, out=o.view(bool)))
        if differ.size:
            src = a[r : r + n].ravel()[differ]
            fixed = np.empty(differ.size, np.uint8)
            _formula(src, lo, scale, np.empty(differ.size, np.float64), fixed)
            dst.ravel()[differ] = fixed
    return True
