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

This module checks the inputs and options and dispatches; the matchers are
:mod:`stereodem.stereo.ncc` and :mod:`stereodem.stereo.sgm`, the score layer
:mod:`stereodem.stereo.score` (:func:`zncc_at`), and what they share
:mod:`stereodem.stereo.window_stats` (window means and standard deviations),
:mod:`stereodem.stereo.seed` (hole-filled seed disparities) and
:mod:`stereodem.stereo.images` (input check, percentiles, column gathers).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from stereodem.core.errors import InputError
from stereodem.stereo.settings import MATCHERS

from .images import _image_and_finite, _robust_range
from .ncc import SUBPIXELS, _match_ncc
from .score import zncc_at
from .sgm import SGM_MODES, _match_sgm

__all__ = ["SGM_MODES", "SUBPIXELS", "MatchResult", "match_rectified", "zncc_at"]

F32 = np.float32


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

    disp, score, extra = _match_sgm(
        left,
        right,
        lo,
        hi,
        range_maps,
        window=window,
        min_score=min_score,
        lr_tolerance=lr_tolerance,
        left_finite=left_finite,
        right_finite=right_finite,
        left_mean=left_mean,
        sgm_mode=sgm_mode,
        sgm_p1=sgm_p1,
        sgm_p2=sgm_p2,
        sgm_uniqueness=sgm_uniqueness,
        sgm_speckle_window=sgm_speckle_window,
        sgm_speckle_range=sgm_speckle_range,
    )
    info.update(sgm_mode=sgm_mode, min_score=min_score, **extra)
    return MatchResult(disp, score, None, info)
