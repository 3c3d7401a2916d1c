"""Settings of the stereo stage, one object per step (the same objects the TOML configuration
and the command line fill in).

* :class:`RectificationSettings` — tiles, height range, epipolar resampling, relative pointing;
* :class:`MatchingSettings` — the dense matcher;
* :class:`RefinementSettings` — the second, warped matching pass;
* :class:`GriddingSettings` — points to the DEM lattice (posting, CRS, estimator).

:class:`StereoSettings` holds the four.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Literal, get_args

#: option choices: the command line, the configuration checks and the docs derive from these
RectificationMethod = Literal["auto", "affine", "projective"]
RECTIFICATION_METHODS: tuple[str, ...] = get_args(RectificationMethod)
Matcher = Literal["sgm", "ncc"]
MATCHERS: tuple[str, ...] = get_args(Matcher)
GriddingMethod = Literal["gaussian", "mean"]
GRIDDING_METHODS: tuple[str, ...] = get_args(GriddingMethod)
#: attitude axes of the jitter correction
JitterAxes = Literal["pitch", "roll", "both"]
JITTER_AXES: tuple[str, ...] = get_args(JitterAxes)
#: N-view DEMs (stereo.fusion): how the pair heights of a cell are fused, and whether the
#: images' models are brought into agreement first
FusionMethod = Literal["weighted", "median"]
FUSION_METHODS: tuple[str, ...] = get_args(FusionMethod)
FusionAdjust = Literal["auto", "always", "never"]
FUSION_ADJUST: tuple[str, ...] = get_args(FusionAdjust)

__all__ = [
    "RectificationSettings",
    "MatchingSettings",
    "RefinementSettings",
    "GriddingSettings",
    "StereoSettings",
]


@dataclass
class RectificationSettings:
    """Tiling, height range and epipolar resampling (:mod:`stereodem.stereo.epipolar`).

    Attributes
    ----------
    tile_size : int
        Side of the left-image tiles, pixels (each is rectified with its own maps).
    height_range : (float, float), optional
        Ellipsoidal heights (m) of the terrain; widened by ``height_margin``. Without it (and
        without a seed DEM) the heights come from sparse matches (``auto_heights``).
    height_margin : float
        Metres added below and above the height range (and a seed DEM's range under a tile),
        0..10000.
    method : {"auto", "affine", "projective"}
        Rectifying maps: affine (pushbroom/RPC, s2p) or projective (frame cameras); auto picks.
    halo : (int, int)
        Columns/rows rectified and matched around each tile (only the tile's points are kept),
        at most ``tile_size`` each.
    disparity_margin : float
        Pixels added to both ends of each tile's disparity range, at most ``tile_size``.
    pointing_correction : bool
        Estimate and remove the relative pointing error of the right image (a translation,
        or an affine correction when the matches support it) from sparse matches searched
        without an epipolar constraint, before rectification
        (:func:`stereodem.stereo.pointing.relative_pointing`).
    pointing_uses_seed : bool
        With a seed DEM, also fix the pointing correction's component along the epipolar
        curves (unobservable from the two images: it is a height offset) by localising the
        matches on the seed DEM: the DEM is then co-registered to the seed vertically.
    auto_heights : bool
        Without a height range or seed DEM, derive both from the sparse matches (a robust
        height range and a coarse seed surface, :func:`stereodem.stereo.terrain.terrain_heights`);
        otherwise the models' whole height validity range is searched.
    sparse_options : dict
        Keyword options of :func:`stereodem.stereo.sparse.sparse_matches` (``max_offset``,
        ``ratio``, ``max_size``, ...); an unknown key or a value of the wrong type or range
        is an error when the configuration is read.
    """

    tile_size: int = 512
    height_range: tuple | None = None
    height_margin: float = 50.0
    method: RectificationMethod = "auto"
    halo: tuple = (32, 16)
    disparity_margin: float = 4.0
    pointing_correction: bool = True
    pointing_uses_seed: bool = False
    auto_heights: bool = True
    sparse_options: dict = field(default_factory=dict)


@dataclass
class MatchingSettings:
    """Dense matching of a rectified tile (:func:`stereodem.stereo.match.match_rectified`).

    Attributes
    ----------
    matcher : {"sgm", "ncc"}
        OpenCV semi-global matching or coarse-to-fine ZNCC.
    options : dict
        Keyword options of :func:`stereodem.stereo.match.match_rectified` (window, min_score,
        ...); an unknown key or a value of the wrong type or range is an error when the
        configuration is read.
    """

    matcher: Matcher = "sgm"
    options: dict = field(default_factory=dict)


@dataclass
class RefinementSettings:
    """Second matching pass on the right image warped by the smoothed first-pass disparity
    (:func:`stereodem.stereo.refine.refine_disparity`).

    Attributes
    ----------
    enabled : bool
        Run the refinement (removes most of the window-distortion error of steep terrain).
    sigma : float
        Smoothing width of the warp, pixels, at most 100 (3 px: Pleiades vs s2p NMAD 0.402 ->
        0.387 m).
    window : int
        ZNCC window of the refinement, odd pixels, 3..255.
    min_score : float, optional
        Minimum ZNCC of a refined match (the refinement's own threshold is 0.5).
    detail_gain : float, optional
        Weight of the warp's sub-window detail (0: window mean, 1: first-pass fine
        structure); None estimates it per tile (Pleiades 0.08-0.32, simulated ASTER 1).
    keep_unrefined : bool
        Keep the first-pass disparity where the refinement found no match, or drop the pixel.
    """

    enabled: bool = True
    sigma: float = 3.0
    window: int = 7
    min_score: float | None = None
    detail_gain: float | None = None
    keep_unrefined: bool = True


@dataclass
class GriddingSettings:
    """Space-intersected points to the DEM lattice (:mod:`stereodem.stereo.grid`).

    Attributes
    ----------
    res : float, optional
        Output posting in the output CRS's units (metres for UTM; default twice the left
        image's GSD, converted to degrees for a geographic CRS).
    crs : CRS-like, optional
        Output CRS (default: the UTM zone of the scene).
    bounds : (xmin, ymin, xmax, ymax), optional
        Output extent in the CRS (default: what the tiles can see).
    geoid : bool
        Write EGM96 geoid heights instead of ellipsoidal heights.
    method : {"gaussian", "mean"}
        Cell estimator; ``gaussian_sigma`` its width in CRS units, 0.1 to 10 postings
        (default: from the point density).
    gaussian_sigma : float, optional
    max_ray_gap : float, optional
        Drop points whose rays miss by more than this (m); default 2 x the left GSD.
    """

    res: float | None = None
    crs: Any = None
    bounds: tuple | None = None
    geoid: bool = False
    method: GriddingMethod = "gaussian"
    gaussian_sigma: float | None = None
    max_ray_gap: float | None = None


@dataclass
class StereoSettings:
    """The four steps' settings of :func:`stereodem.stereo.pipeline.make_dem`."""

    rectification: RectificationSettings = field(default_factory=RectificationSettings)
    matching: MatchingSettings = field(default_factory=MatchingSettings)
    refinement: RefinementSettings = field(default_factory=RefinementSettings)
    gridding: GriddingSettings = field(default_factory=GriddingSettings)

    def summary(self) -> dict:
        """Plain-JSON form (CRS as text)."""
        d = asdict(self)
        d["gridding"]["crs"] = None if self.gridding.crs is None else str(self.gridding.crs)
        return d
