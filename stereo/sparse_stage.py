"""The sparse stage of a stereo run: sparse matches -> relative pointing -> terrain heights.

Runs before rectification (CARS and s2p do the same): SIFT matches checked through the models
(:mod:`stereodem.stereo.sparse`), the relative pointing correction of the right model
(:mod:`stereodem.stereo.pointing`), and, when the user gave no height range or seed DEM, the
scene's height range and a coarse seed surface (:mod:`stereodem.stereo.terrain`) from the same
matches intersected with the corrected models.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .pointing import PointingCorrection, relative_pointing
from .sparse import SparseMatches, sparse_matches
from .terrain import TerrainHeights, terrain_heights

log = logging.getLogger(__name__)

__all__ = ["SparseStage", "run_sparse_stage", "height_pileup"]


@dataclass
class SparseStage:
    """Result of :func:`run_sparse_stage`.

    Attributes
    ----------
    right_model : SensorModel
        The right model to use downstream (pointing-corrected when the correction ran).
    height_range : (float, float) or None
        Scene height range found (m, ellipsoidal), when terrain heights ran.
    matches, pointing, terrain : optional
        The stages' results (None when skipped).
    seconds : dict
        Wall time per stage.
    """

    right_model: object
    height_range: tuple | None
    matches: SparseMatches | None = None
    pointing: PointingCorrection | None = None
    terrain: TerrainHeights | None = None
    seconds: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Plain-dict record for the run report."""
        out = dict(seconds={k: round(v, 3) for k, v in self.seconds.items()})
        if self.matches is not None:
            out["matches"] = dict(
                n=len(self.matches),
                **{k: v for k, v in self.matches.info.items() if k != "seconds"},
            )
        if self.pointing is not None:
            out["pointing"] = self.pointing.summary()
        if self.terrain is not None:
            out["terrain"] = self.terrain.summary()
        return out


def run_sparse_stage(
    left_image,
    right_image,
    left_model,
    right_model,
    *,
    heights: bool = True,
    pointing: bool = True,
    height_range=None,
    reference_dem=None,
    max_offset: float = 50.0,
    **match_options,
) -> SparseStage:
    """Sparse matches, then the pointing correction and/or the terrain heights.

    Parameters
    ----------
    heights : bool
        Derive the height range and seed surface (when the user gave neither).
    pointing : bool
        Estimate the relative pointing correction of the right model.
    height_range : (float, float), optional
        Heights to check the matches over (default the models' validity range).
    reference_dem : DEM, optional
        Fixes the pointing correction along the epipolar curves.
    max_offset : float
        Largest relative image offset (px) the sparse check allows.
    **match_options
        Passed to :func:`stereodem.stereo.sparse.sparse_matches`.

    Raises :class:`SparseMatchError` (one line) when the matches do not suffice.
    """
    seconds = {}
    t0 = time.perf_counter()
    m = sparse_matches(
        left_image,
        right_image,
        left_model,
        right_model,
        height_range,
        max_offset=max_offset,
        **match_options,
    )
    seconds["matching"] = time.perf_counter() - t0
    right = right_model
    pc = None
    if pointing:
        t1 = time.perf_counter()
        pc = relative_pointing(m, left_model, right_model, reference_dem=reference_dem)
        right = pc.model
        seconds["pointing"] = time.perf_counter() - t1
    th = None
    if heights:
        t2 = time.perf_counter()
        th = terrain_heights(m, left_model, right)
        seconds["terrain"] = time.perf_counter() - t2
    seconds["total"] = time.perf_counter() - t0
    return SparseStage(right, th.height_range if th is not None else None, m, pc, th, seconds)


def height_pileup(h, height_range, *, band: float = 0.02, max_share: float = 0.05) -> dict:
    """Share of heights piled at either bound of the search range.

    A dense matcher confined to a height range that misses the terrain (or searching along
    lines that miss their match) returns heights stuck at the bounds. ``band`` is the
    fraction of the range counted as "at" a bound; the result is ``suspect`` when either
    share exceeds ``max_share`` (a share of ``band`` is what heights spread evenly over the
    range would give; the default flags 2.5 times that).

    Returns
    -------
    dict
        ``low_share``, ``high_share`` (fractions of the finite heights), ``suspect`` (bool),
        ``n`` (finite heights).
    """
    h = np.asarray(h, float)
    h = h[np.isfinite(h)]
    lo, hi = (float(v) for v in height_range)
    if h.size == 0 or not hi > lo:
        return dict(low_share=0.0, high_share=0.0, suspect=False, n=int(h.size))
    width = band * (hi - lo)
    low = float(np.mean(h <= lo + width))
    high = float(np.mean(h >= hi - width))
    return dict(
        low_share=low, high_share=high, suspect=bool(max(low, high) > max_share), n=int(h.size)
    )
