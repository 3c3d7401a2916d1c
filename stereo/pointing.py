"""Relative pointing: the right image's translation that removes the vertical parallax of
matches (s2p's pointing correction), estimated before the tiles are matched.
"""
from __future__ import annotations

import logging

import numpy as np

from . import epipolar
from .plan import tile_height_range
from .settings import RectificationSettings

log = logging.getLogger(__name__)

__all__ = ["estimate_pointing"]


def estimate_pointing(tiles, inputs, settings: RectificationSettings, *, n_tiles: int = 4,
                      min_score: float = 0.7, vertical_search: int = 2):
    """Relative pointing error of the right image, as an image translation (pixels).

    On up to ``n_tiles`` tiles spread over the list, the rectified pair is matched by ZNCC
    with a vertical search of ``+/- vertical_search`` px; the vertical offsets of confident
    matches (score >= ``min_score``) are turned into right-image displacements
    (:func:`stereodem.stereo.epipolar.vertical_offset_to_image_shift`), and their median over all tiles is
    the correction (s2p: per-tile translations, then a global median). Only the component
    across the epipolar lines is observable; along them a shift is a height change.

    Returns ``(dcol, drow, info)``; apply with ``ImageCorrectedModel(right, col_shift=dcol, row_shift=drow)``.
    """
    from .match import match_rectified

    if not tiles:
        return 0.0, 0.0, dict(n_matches=0)
    pick = np.unique(np.linspace(0, len(tiles) - 1, min(n_tiles, len(tiles))).round().astype(int))
    dcs, drs = [], []
    for k in pick:
        tile = tiles[k]
        hr = tile_height_range(tile, inputs, settings.height_margin)
        et = epipolar.rectify_tile(inputs.left_model, inputs.right_model, tile, hr,
                                   halo=settings.halo, method=settings.method,
                                   disparity_margin=settings.disparity_margin)
        lr, rr = et.rectify(inputs.left_image, inputs.right_image)
        if not (np.isfinite(lr).any() and np.isfinite(rr).any()):
            continue
        m = match_rectified(lr, rr, et.disparity_range, "ncc", vertical_search=vertical_search)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(m.disparity) & np.isfinite(m.vertical) & (m.score >= min_score)
            ok &= np.abs(m.vertical) < vertical_search - 0.25        # not stuck at the edge
        v, u = np.nonzero(ok)
        dc, dr = epipolar.vertical_offset_to_image_shift(et, u.astype(float), v.astype(float),
                                                         m.disparity[v, u], m.vertical[v, u])
        dcs.append(dc)
        drs.append(dr)
    dc = np.concatenate(dcs) if dcs else np.zeros(0)
    dr = np.concatenate(drs) if drs else np.zeros(0)
    if dc.size < 100:
        log.warning("relative pointing: too few confident matches (%d); no correction", dc.size)
        return 0.0, 0.0, dict(n_matches=int(dc.size))
    dcol, drow = float(np.median(dc)), float(np.median(dr))
    info = dict(n_matches=int(dc.size), dcol_px=dcol, drow_px=drow,
                spread_px=float(1.4826 * np.median(np.abs(np.hypot(dc - dcol, dr - drow)))))
    log.info("relative pointing correction of the right image: dcol %.3f px, drow %.3f px "
             "(%d matches)", dcol, drow, dc.size)
    return dcol, drow, info
