"""Cloud masks of one DEM (ASTER DEMs over clouds are blunders of hundreds of metres).

Three independent signs, each a boolean raster on the DEM's grid, combined and grown by a few
cells (the matcher's window smears a cloud's edge into the terrain around it):

* **radiance**: clouds are bright in the near-infrared nadir band (3N); cells whose 3N
  radiance (W m⁻² sr⁻¹ µm⁻¹, the orthoimage of the granule's radiance) exceeds
  ``max_radiance``;
* **matcher score**: cells whose correlation score (``score.tif`` of ``stereodem dem``, 0..1)
  is below ``min_score`` (clouds move between the 3N and 3B looks, 55 s apart, and have little
  texture);
* **deviation**: cells whose height differs from the reference (or from the stack's temporal
  median) by more than ``max_deviation`` metres after removing the median difference.

:class:`CloudSettings` holds the thresholds; :func:`cloud_mask` returns the combined mask and
the fraction each sign flagged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from stereodem.core.errors import InputError
from stereodem.core.stats import nanmedian, nmad


@dataclass(frozen=True)
class CloudSettings:
    """Thresholds of the cloud mask; ``None`` turns a sign off.

    Attributes
    ----------
    max_deviation : float or None
        Metres from the reference (median difference removed); default 50.
    min_score : float or None
        Lowest matcher score kept (0..1); default None (off).
    max_radiance : float or None
        Highest 3N radiance kept (W m-2 sr-1 um-1); default None (off).
    grow : int
        Cells the combined mask is grown by (default 3).
    """

    max_deviation: float | None = 50.0
    min_score: float | None = None
    max_radiance: float | None = None
    grow: int = 3

    def __post_init__(self):
        if self.max_deviation is not None and not self.max_deviation > 0:
            raise InputError(f"cloud max_deviation must be positive, got {self.max_deviation}")
        if self.min_score is not None and not 0 <= self.min_score <= 1:
            raise InputError(f"cloud min_score must be in [0, 1], got {self.min_score}")
        if self.max_radiance is not None and not self.max_radiance > 0:
            # NaN compared false with every radiance: the sign was off without a word
            raise InputError(f"cloud max_radiance must be positive, got {self.max_radiance}")
        if self.grow < 0:
            raise InputError(f"cloud grow must be >= 0 cells, got {self.grow}")


#: grows of more cells than this take the distance transform (one pass whatever the grow)
#: instead of repeated 3 x 3 cross dilations (one pass per cell of growth); the same cells
GROW_BY_DISTANCE = 16


def grow_mask(mask, cells: int) -> np.ndarray:
    """``mask`` grown by ``cells`` cells: every cell within a city-block distance of
    ``cells`` of a True cell, as ``cells`` iterations of a 3 x 3 cross dilation. Beyond
    :data:`GROW_BY_DISTANCE` cells as the city-block distance transform, whose cost does not
    grow with ``cells`` (a grow of 10^11 cells was an OverflowError from scipy's iteration
    count; 10^4 would have run 10^4 passes)."""
    if cells <= 0 or not mask.any():
        return mask
    if cells <= GROW_BY_DISTANCE:
        return ndimage.binary_dilation(mask, iterations=cells)
    # no distance in the grid exceeds rows + cols: a larger grow is that one
    reach = min(cells, sum(mask.shape))
    return ndimage.distance_transform_cdt(~mask, metric="taxicab") <= reach


def deviation_mask(heights, reference, max_deviation: float, *, stable=None) -> np.ndarray:
    """Cells where ``heights − reference`` departs from its median (over ``stable`` cells when
    given) by more than ``max_deviation`` metres."""
    dh = np.asarray(heights, np.float32) - np.asarray(reference, np.float32)
    sel = np.isfinite(dh) if stable is None else np.isfinite(dh) & stable
    if not sel.any():
        return np.zeros(dh.shape, bool)
    med = np.float32(np.median(dh[sel]))
    with np.errstate(invalid="ignore"):
        return np.abs(dh - med) > max_deviation


def score_mask(score, min_score: float) -> np.ndarray:
    """Cells whose matcher score is below ``min_score`` (NaN scores are not flagged)."""
    with np.errstate(invalid="ignore"):
        return np.asarray(score, np.float32) < min_score


def radiance_mask(radiance, max_radiance: float) -> np.ndarray:
    """Cells brighter than ``max_radiance`` (W m-2 sr-1 um-1)."""
    with np.errstate(invalid="ignore"):
        return np.asarray(radiance, np.float32) > max_radiance


def temporal_deviation(stack, max_deviation: float) -> np.ndarray:
    """Observations of a stack ``(T, ...)`` farther than ``max_deviation`` metres from their
    cell's temporal median (the stack's own blunder test; :mod:`stereodem.post.rates` applies
    it per cell before fitting)."""
    med = nanmedian(stack, axis=0)
    with np.errstate(invalid="ignore"):
        return np.abs(np.asarray(stack) - med) > max_deviation


def cloud_mask(
    heights,
    *,
    settings: CloudSettings = CloudSettings(),
    reference=None,
    score=None,
    radiance=None,
    stable=None,
):
    """The combined cloud mask of one DEM and what flagged it.

    Returns
    -------
    mask : ndarray bool
        Grown by ``settings.grow`` cells.
    info : dict
        Percent of the valid cells flagged by each sign (``deviation_pct``, ``score_pct``,
        ``radiance_pct``) and in all after growing (``cloud_pct``); ``dh_nmad`` of the
        unflagged cells against the reference (m) when there is one.
    """
    h = np.asarray(heights, np.float32)
    valid = np.isfinite(h)
    n = max(int(valid.sum()), 1)
    parts, info = [], {}
    for name, layer, thr, fn in (
        (
            "deviation",
            reference,
            settings.max_deviation,
            lambda a, t: deviation_mask(h, a, t, stable=stable),
        ),
        ("score", score, settings.min_score, score_mask),
        ("radiance", radiance, settings.max_radiance, radiance_mask),
    ):
        if layer is None or thr is None:
            continue
        if np.shape(layer) != h.shape:
            raise InputError(
                f"cloud mask: the {name} layer is {np.shape(layer)}, the DEM {h.shape}"
            )
        m = fn(layer, thr) & valid
        info[f"{name}_pct"] = round(100.0 * m.sum() / n, 4)
        parts.append(m)
    mask = np.zeros(h.shape, bool)
    for m in parts:
        mask |= m
    if settings.grow and mask.any():
        mask = grow_mask(mask, int(settings.grow)) & valid
    info["cloud_pct"] = round(100.0 * mask.sum() / n, 4)
    if reference is not None:
        info["dh_nmad"] = nmad((h - np.asarray(reference, np.float32))[valid & ~mask])
    return mask, info
