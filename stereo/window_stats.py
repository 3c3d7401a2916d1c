"""Window statistics of float32 images with NaN no-data: the box mean of each window and
its standard deviation (or inverse), the terms of a ZNCC, by OpenCV's separable filters and
element-wise passes in row bands that stay in cache; the floors of the variances and of the
product of two standard deviations; the NaN border of windows leaving the image."""

from __future__ import annotations

import functools
from typing import NamedTuple

import cv2
import numpy as np

from stereodem.core.morphology import square_dilation

F32 = np.float32
_SQRT_TINY = np.sqrt(F32(1e-30))  # the variance floor's square root, float32
_TINY = F32(1e-30)  # the floor of the score's product of two standard deviations


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
