"""The ``"sgm"`` matcher: OpenCV's semi-global matcher (``cv2.StereoSGBM``) with its
conventions handled (``numDisparities`` a multiple of 16, 1/16 fixed-point output,
``minDisparity`` for negative ranges, 8-bit input by a joint percentile stretch, edge padding
so that every column that can have a match is matched, no match outside the right image or
beyond the requested range); its score layer is the ZNCC at the SGM disparity
(:mod:`.score`)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from stereodem.core.stretch import linear_to_uint8

from .images import _col_index, _finite_sample, _gather_cols, _percentiles
from .score import _zncc_left, _zncc_warped

F32 = np.float32


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

#: ``sgm_mode`` choices of :func:`stereodem.stereo.match.match_rectified`
SGM_MODES: tuple[str, ...] = tuple(_SGBM_MODES)


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


def _match_sgm(
    left,
    right,
    lo,
    hi,
    range_maps,
    *,
    window,
    min_score,
    lr_tolerance,
    left_finite,
    right_finite,
    left_mean,
    sgm_mode,
    sgm_p1,
    sgm_p2,
    sgm_uniqueness,
    sgm_speckle_window,
    sgm_speckle_range,
):
    """The ``"sgm"`` matcher of :func:`stereodem.stereo.match.match_rectified` on checked
    float32 images: ``cv2.StereoSGBM`` on the 8-bit stretch (:func:`_to_uint8`,
    :func:`_sgbm`), no-data windows removed, the ZNCC score layer at the SGM disparity
    (:mod:`.score`), the per-pixel range and ``min_score`` applied.  ``left_finite``,
    ``right_finite``, ``left_mean``: :func:`stereodem.stereo.images._image_and_finite`'s.
    Returns the disparity, the score and the info entries of this matcher."""
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
    return disp, score, {"score_window": score_window}
