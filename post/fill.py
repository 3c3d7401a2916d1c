"""Hole filling and smoothing of DEM grids.

Small holes (fewer than ``max_hole_size`` cells, the Ok (2005) recipe used < 200 pixels) are
filled by inverse-distance weighting of the nearest valid cells on their rims. Larger holes
stay NaN unless a fallback DEM on the same grid is given: then they take the fallback heights
plus the DEM − fallback offset interpolated (inverse distance) from the hole's rim, so the seam
is continuous. Optional Gaussian smoothing ignores voids (normalised convolution). Each filled
cell is flagged in a uint8 layer: :data:`FILLED_IDW` or :data:`FILLED_FALLBACK`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from stereodem.core.blocks import by_rows, default_threads
from stereodem.core.errors import InputError
from stereodem.core.morphology import square_dilation

log = logging.getLogger(__name__)

ORIGINAL, FILLED_IDW, FILLED_FALLBACK = 0, 1, 2


@dataclass
class FillResult:
    """Output of :func:`fill_holes`.

    Attributes
    ----------
    heights : ndarray float32, NaN where still void.
    filled : ndarray uint8, 0 original/void, 1 filled by IDW, 2 filled from the fallback DEM.
    report : dict, counts and parameters.
    """

    heights: np.ndarray
    filled: np.ndarray
    report: dict


def _idw(points_rc, values, query_rc, *, k: int, power: float):
    tree = cKDTree(points_rc)
    k = int(min(k, len(points_rc)))

    d, i = tree.query(query_rc, k=k, workers=default_threads())  # per query: same values
    if k == 1:
        d, i = d[:, None], i[:, None]
    w = 1.0 / np.maximum(d, 1e-9) ** power
    return np.sum(w * values[i], axis=1) / np.sum(w, axis=1)


def idw_fill(heights, holes, *, k: int = 12, power: float = 2.0):
    """Inverse-distance fill of the cells of ``holes`` from the valid cells on their rims.

    ``k`` nearest rim cells (8-connected rim of the holes) weighted by 1/d^power.
    Returns a float64 copy of ``heights`` with the hole cells filled.
    """
    z = np.asarray(heights, dtype=np.float64).copy()
    _idw_fill_into(z, np.asarray(holes, bool), k=k, power=power)
    return z


def _idw_fill_into(z, holes, *, k: int, power: float):
    """:func:`idw_fill` in place on the float64 grid ``z``."""
    if not holes.any():
        return
    rim = square_dilation(holes, 3) & np.isfinite(z)  # the holes' 8 neighbours
    if not rim.any():
        raise InputError("holes have no valid rim to interpolate from")
    pr = np.column_stack(np.nonzero(rim)).astype(np.float64)
    q = np.column_stack(np.nonzero(holes)).astype(np.float64)
    z[holes] = _idw(pr, z[rim], q, k=k, power=power)


def fill_holes(
    heights,
    *,
    max_hole_size: int = 200,
    grow: int = 0,
    fallback=None,
    k: int = 12,
    power: float = 2.0,
) -> FillResult:
    """Fill voids of a DEM grid.

    Parameters
    ----------
    heights : ndarray (rows, cols), NaN voids.
    max_hole_size : int
        Holes (8-connected void components) with fewer cells are filled by IDW; larger ones
        stay void unless ``fallback`` is given.
    grow : int
        Grow every void by this many cells before filling (the thesis grew failures by 1 px
        to drop the unreliable edge cells around them).
    fallback : ndarray, optional
        Heights on the same grid and vertical reference (e.g. a reprojected SRTM) for the large
        holes; the seam is blended by interpolating the DEM − fallback offset from the rim.
    """
    z = np.asarray(heights, dtype=np.float64).copy()
    if z.ndim != 2:
        raise InputError(f"expected a 2-D height grid, got shape {z.shape}")
    if grow > 0:
        void = ~np.isfinite(z)
        # ``grow`` 8-neighbour steps: the cells within ``grow`` cells (Chebyshev) of a void
        z[square_dilation(void, 2 * int(grow) + 1)] = np.nan
    void = ~np.isfinite(z)
    filled = np.zeros(z.shape, np.uint8)
    report = {
        "max_hole_size": int(max_hole_size),
        "grow": int(grow),
        "k": int(k),
        "power": power,
        "holes": 0,
        "small_holes": 0,
        "filled_idw": 0,
        "filled_fallback": 0,
        "left_void": 0,
    }
    if not void.any():
        return FillResult(z.astype(np.float32), filled, report)
    if not np.isfinite(z).any():
        raise InputError("the DEM has no valid height to fill from")
    # the holes: 8-connected components of the voids (OpenCV's labelling, with their sizes)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(
        void.view(np.uint8), connectivity=8, ltype=cv2.CV_32S
    )
    small_ids = np.zeros(n, bool)  # label 0: the valid cells
    small_ids[1:] = stats[1:, cv2.CC_STAT_AREA] < max_hole_size
    small = small_ids[lab]
    del lab
    large = void & ~small
    report.update(holes=int(n - 1), small_holes=int(small_ids.sum()))
    if small.any():
        _idw_fill_into(z, small, k=k, power=power)
        filled[small] = FILLED_IDW
    if large.any() and fallback is not None:
        fb = np.asarray(fallback, dtype=np.float64)
        if fb.shape != z.shape:
            raise InputError(f"fallback DEM has shape {fb.shape}, the DEM {z.shape}")
        offset = z - fb  # defined where both are valid
        cover = large & np.isfinite(fb)
        rim = square_dilation(large, 3) & np.isfinite(offset)
        if cover.any() and rim.any():
            pr = np.column_stack(np.nonzero(rim)).astype(np.float64)
            q = np.column_stack(np.nonzero(cover)).astype(np.float64)
            z[cover] = fb[cover] + _idw(pr, offset[rim], q, k=k, power=power)
            filled[cover] = FILLED_FALLBACK
        elif cover.any():
            z[cover] = fb[cover]
            filled[cover] = FILLED_FALLBACK
    report.update(
        filled_idw=int((filled == FILLED_IDW).sum()),
        filled_fallback=int((filled == FILLED_FALLBACK).sum()),
        left_void=int((~np.isfinite(z)).sum()),
    )
    log.info(
        "hole filling: %(filled_idw)d cells by IDW, %(filled_fallback)d from the fallback, "
        "%(left_void)d left void",
        report,
    )
    return FillResult(z.astype(np.float32), filled, report)


def gaussian_smooth(heights, *, sigma: float = 0.85, passes: int = 1, truncate: float = 1.2):
    """Gaussian smoothing that ignores voids (normalised convolution); voids stay void.

    The defaults approximate the 3 × 3 Gaussian kernel of the Ok (2005) recipe, which applied
    it twice (``passes=2``). ``sigma`` is in cells.
    """
    z = np.asarray(heights, dtype=np.float64)
    valid = np.isfinite(z)
    out = z.copy()

    halo = int(truncate * float(sigma) + 0.5)  # scipy's kernel radius

    def gauss(a):  # in row bands on threads
        return by_rows(
            lambda b: ndi.gaussian_filter(b, sigma, mode="nearest", truncate=truncate), a, halo=halo
        )

    for _ in range(int(passes)):
        w = gauss(valid.astype(np.float64))
        s = gauss(np.where(valid, out, 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(valid, s / w, np.nan)
    return out.astype(np.float32)
