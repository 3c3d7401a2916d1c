"""Per-tile stereo DEM workflow: rectify, match, refine, intersect, grid (s2p style).

:func:`make_dem` reads top to bottom: inputs and height range (:mod:`.plan`), overlap of the
two images, the sparse stage (:mod:`.sparse_stage`: SIFT matches checked through the models,
the relative pointing correction of the right model, and — without a height range or seed
DEM — the scene's height range and a coarse seed surface), the tiles over the overlap at every
height of the range, the output lattice, then for every tile :func:`process_tile` (a pure function
of the tile, the inputs and the settings, so tiles can run in a process pool), and finally the
tiles' cell sums added into the DEM. Per tile:

1. height range (the settings' range, or the seed DEM — given, or from the sparse matches —
   under the tile plus a margin);
2. epipolar rectification (:func:`stereodem.stereo.epipolar.rectify_tile`) and resampling of
   both images; the disparity search range comes from the height range;
3. dense matching (:func:`stereodem.stereo.match.match_rectified`) and refinement
   (:func:`stereodem.stereo.refine.refine_disparity`);
4. matched pixels back to each image's own coordinates, and space intersection with the
   exact models (:func:`stereodem.sensor.geo.intersect.intersect_matches`); points whose rays miss
   each other by more than the maximum ray gap are dropped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from stereodem.core import geodesy, localfit
from stereodem.core.dem import DEM, as_dem
from stereodem.core.errors import InputError
from stereodem.core.grid import crs_unit, map_crs, posting_text
from stereodem.core.jsonutil import json_default
from stereodem.core.memory import check_allocation
from stereodem.sensor.geo.intersect import intersect_matches
from stereodem.sensor.models.base import pair_height_bounds

from . import epipolar
from .grid import SUM_LAYERS, CellSums, GridSpec, accumulate, finish
from .match import match_rectified
from .plan import footprint_bounds, overlap_window, pair_height_range, plan_tiles, tile_height_range
from .pointcloud import save_tile_points
from .refine import refine_disparity
from .sanity import check_pair
from .settings import (
    MATCHERS,
    GriddingSettings,
    MatchingSettings,
    RectificationSettings,
    RefinementSettings,
    StereoSettings,
)
from .sparse import SparseMatchError
from .sparse_stage import height_pileup, run_sparse_stage
from .tiling import Tile, tile_order

log = logging.getLogger(__name__)

__all__ = [
    "PairInputs",
    "TilePoints",
    "TileResult",
    "DEMProducts",
    "make_dem",
    "process_tile",
    "tile_points",
]


@dataclass
class PairInputs:
    """Everything a tile needs, read-only: images (arrays, memory maps or anything sliceable
    with a ``shape``), models, the height range and the output lattice."""

    left_image: Any
    right_image: Any
    left_model: Any
    right_model: Any
    height_range: tuple
    seed_dem: DEM | None = None
    max_ray_gap: float = np.inf
    lattice: GridSpec | None = None
    seed_margin: float | None = None
    points_dir: str | None = None  # tiles also write their points here (point clouds)
    pair_id: int = 0  # the pair's index in the points (source_pair)


@dataclass
class TilePoints:
    """Ground points of one tile (degrees, metres above the ellipsoid) with their score and
    ray gap (m), and the tile's QA figures (``summary``: rectification, counts, timings)."""

    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    score: np.ndarray
    ray_gap: np.ndarray
    summary: dict


@dataclass
class TileResult:
    """One tile's contribution to the DEM: its points' weighted sums on a window of the output
    lattice (:class:`stereodem.stereo.grid.CellSums`, a few MB whatever the scene size) and its
    QA."""

    cells: CellSums
    summary: dict

    def to_arrays(self) -> dict:
        """Plain arrays (cacheable with ``np.savez``, no pickle): the cell sums, their window
        origin and point count, the QA summary as JSON."""
        c = self.cells
        return dict(
            sums=c.sums,
            origin=np.array([c.row0, c.col0, c.n_points], np.int64),
            summary=np.array(json.dumps(self.summary, default=json_default)),
        )

    @classmethod
    def from_arrays(cls, arrays) -> TileResult:
        """The :class:`TileResult` of :meth:`to_arrays`' output (or a loaded ``.npz``)."""
        r0, c0, n = (int(v) for v in arrays["origin"])
        return cls(CellSums(r0, c0, arrays["sums"], n), json.loads(str(arrays["summary"])))


@dataclass
class StereoInfo:
    """Run figures of :func:`make_dem` (typed; :meth:`to_dict` is what the reports store).

    Attributes
    ----------
    height_range : list of float
        Heights searched, metres (ellipsoidal): ``[min, max]``.
    gsd_m, posting, max_ray_gap_m : float
        Ground sample distance of the left image (m), output posting (CRS units), ray-gap
        limit (m).
    n_tiles : int
    max_residual_rms_px : float
        Largest per-tile RMS y-parallax after rectification, pixels.
    valid_cells : float
        Share (0..1) of the lattice's cells with a height.
    pointing, sparse : dict
        Relative pointing correction and sparse stage summaries (``sparse`` None when skipped).
    height_source : str
        ``"sparse matches"``, ``"seed DEM"``, ``"height range"`` or ``"model validity range"``.
    height_margin_m : float
        The margin (m) the range of the sparse matches, the seed DEM or the settings was
        widened by each side (``RectificationSettings.height_margin``; 0 for the models'
        validity range), before the range was kept within the models' validity range.
    height_pileup : dict
        :func:`stereodem.stereo.sparse_stage.height_pileup`; ``suspect`` its verdict.
    jitter : dict, optional
        Per axis, the fitted attitude oscillation (jitter correction only).
    base_to_height : float, optional
        From :func:`stereodem.stereo.sanity.check_pair`.
    warnings : list of dict
        Sanity findings (:class:`stereodem.stereo.sanity.Finding`); ``status`` ``"ok"`` or
        ``"suspect"``.
    """

    height_range: list
    gsd_m: float
    posting: float
    max_ray_gap_m: float
    n_tiles: int
    max_residual_rms_px: float
    valid_cells: float
    pointing: dict
    sparse: dict | None
    height_source: str
    height_pileup: dict
    suspect: bool
    height_margin_m: float = 0.0
    jitter: dict | None = None
    base_to_height: float | None = None
    warnings: list = field(default_factory=list)
    status: str = "ok"

    def to_dict(self) -> dict:
        """The figures as a JSON-ready dict (``jitter`` only when estimated)."""
        d = dataclasses.asdict(self)
        if d["jitter"] is None:
            del d["jitter"]
        return d


@dataclass
class DEMProducts:
    """Output of :func:`make_dem`: the DEM and its layers, the per-tile QA and run figures."""

    dem: DEM
    tiles: list
    n_points: int
    seconds: float
    settings: dict
    info: StereoInfo

    def write(self, directory, *, overwrite=False, creation_options=None, tags=None, threads=1):
        """Write ``dem.tif``, ``score.tif``, ``count.tif``, ``raygap.tif`` in ``directory``
        (``tags``: dataset tags of ``dem.tif``; ``threads``: files written at a time,
        :meth:`stereodem.core.dem.DEM.prepare_write`); returns ``{"dem": path, "count": path,
        ...}``."""
        return self.dem.prepare_write(
            Path(directory) / "dem.tif",
            overwrite=overwrite,
            creation_options=creation_options,
            tags=tags,
            threads=threads,
        )()


# ----------------------------------------------------------------------------- one tile


def process_tile(tile: Tile, inputs: PairInputs, settings: StereoSettings) -> TileResult:
    """Rectify, match, intersect and grid one tile (:func:`tile_points`, then the points'
    weighted sums on ``inputs.lattice``).

    Pure function of its arguments (no global state; no I/O unless ``inputs.points_dir``
    asks for the tile's points in a file: :mod:`.pointcloud`), so it can run in a worker
    process; what it returns is small (cell sums, not points).
    """
    pts = tile_points(tile, inputs, settings)
    if inputs.points_dir is not None:
        save_tile_points(
            inputs.points_dir,
            tile.index,
            pts.lon,
            pts.lat,
            pts.h,
            pts.score,
            pts.ray_gap,
            crs=inputs.lattice.grid.crs,
            geoid=inputs.lattice.geoid,
            pair=inputs.pair_id,
        )
    t0 = time.perf_counter()
    cells = accumulate(
        inputs.lattice, pts.lon, pts.lat, pts.h, score=pts.score, ray_gap=pts.ray_gap
    )
    if isinstance(pts.summary.get("seconds"), dict):
        pts.summary["seconds"]["grid"] = time.perf_counter() - t0
    return TileResult(cells, pts.summary)


def no_point_matched(
    tiles, settings: StereoSettings, failures=(), summaries=(), max_ray_gap=None
) -> InputError:
    """The error of a pair whose tiles gave no point: the tiles' own error when every tile
    failed (it was hidden behind "no point was matched"), the space intersection's limits
    when the tiles matched points but kept none (``summaries``: the tiles' QA summaries;
    ``max_ray_gap``: the ray-gap limit, m), else the likely causes, with the ``[matching]
    options`` given (a threshold or window that rejects every match)."""
    failures = list(failures)
    if failures and len(failures) >= len(tiles):
        return InputError(
            f"every tile failed ({len(failures)}); the first (tile {failures[0].tile.index}): "
            f"{failures[0].reason}"
        )
    n_matched = sum(int(s.get("n_matched", 0)) for s in summaries)
    if n_matched:
        gap = f"the {max_ray_gap:g} m" if max_ray_gap is not None else "the"
        return InputError(
            f"the tiles matched {n_matched} point(s) but kept none: every one's rays miss by "
            f"more than {gap} limit ([gridding] max_ray_gap) or its height lies outside "
            "the search range"
        )
    causes = "no texture, or a wrong height range"
    options = settings.matching.options
    if options:
        given = ", ".join(f"{k} = {v!r}" for k, v in options.items())
        causes += f", or [matching] options that reject every match ({given})"
    return InputError(f"no point was matched in any tile ({causes}?)")


def rectify_pair_tile(tile: Tile, inputs: PairInputs, rect):
    """The epipolar rectification (:func:`stereodem.stereo.epipolar.rectify_tile`) of ``tile`` of
    the left image with the ``[rectification]`` settings ``rect`` (halo in pixels, method,
    disparity margin), over the tile's height range (m, ellipsoidal:
    :func:`~stereodem.stereo.plan.tile_height_range` with ``rect.height_margin``). Returns
    ``(EpipolarTile, height range)``."""
    hr = tile_height_range(tile, inputs, rect.height_margin)
    et = epipolar.rectify_tile(
        inputs.left_model,
        inputs.right_model,
        tile,
        hr,
        halo=rect.halo,
        method=rect.method,
        disparity_margin=rect.disparity_margin,
    )
    return et, hr


def tile_points(tile: Tile, inputs: PairInputs, settings: StereoSettings) -> TilePoints:
    """Rectify, match and intersect one tile; returns its ground points and QA summary."""
    t0 = time.perf_counter()
    rect, ref = settings.rectification, settings.refinement
    L, R = inputs.left_model, inputs.right_model
    et, hr = rectify_pair_tile(tile, inputs, rect)
    left_r, right_r = et.rectify(inputs.left_image, inputs.right_image)
    t1 = time.perf_counter()
    summary = et.summary()
    empty = np.zeros(0)
    if not (np.isfinite(left_r).any() and np.isfinite(right_r).any()):
        summary.update(n_matched=0, n_points=0, seconds=time.perf_counter() - t0)
        return TilePoints(empty, empty, empty, empty, empty, summary)
    m = match_rectified(
        left_r, right_r, et.disparity_range, settings.matching.matcher, **settings.matching.options
    )
    disparity, score_map, vertical = m.disparity, m.score, m.vertical
    if ref.enabled and vertical is None:
        d_ref, s_ref, gain = refine_disparity(
            left_r,
            right_r,
            disparity,
            sigma=ref.sigma,
            window=ref.window,
            detail_gain=ref.detail_gain,
        )
        summary["refine_detail_gain"] = gain
        good = np.isfinite(d_ref)
        if ref.min_score is not None:
            with np.errstate(invalid="ignore"):
                good &= s_ref >= ref.min_score
        if ref.keep_unrefined:
            # keep the first pass where the refinement found nothing
            disparity = np.where(good, d_ref, disparity)
            score_map = np.where(good, s_ref, score_map)
        else:
            disparity = np.where(good, d_ref, np.nan).astype(np.float32)
            score_map = s_ref
    t2 = time.perf_counter()
    v, u = np.nonzero(np.isfinite(disparity))
    d = disparity[v, u].astype(np.float64)
    score = score_map[v, u].astype(np.float64)
    vert = 0.0 if vertical is None else vertical[v, u].astype(np.float64)
    c1, r1 = epipolar.apply_map(np.linalg.inv(et.H_left), u, v)
    # right point: (u - d, v - vertical) in the rectified frame
    c2, r2 = epipolar.apply_map(np.linalg.inv(et.H_right), u - d, v - vert)
    keep = tile.contains(c1, r1)
    c1, r1, c2, r2, score = c1[keep], r1[keep], c2[keep], r2[keep], score[keep]
    pts = intersect_matches(L, R, c1, r1, c2, r2, tolerance_m=localfit.TILE_TOLERANCE_M)
    ok = np.isfinite(pts.h) & (pts.ray_gap <= inputs.max_ray_gap)
    ok &= (pts.h >= hr[0] - rect.height_margin) & (pts.h <= hr[1] + rect.height_margin)
    t3 = time.perf_counter()
    pile = height_pileup(pts.h[ok], hr)
    summary.update(
        n_matched=int(keep.sum()),
        n_points=int(ok.sum()),
        height_range=list(hr),
        n_at_low_bound=int(round(pile["low_share"] * pile["n"])),
        n_at_high_bound=int(round(pile["high_share"] * pile["n"])),
        valid_fraction=float(ok.sum() / max(tile.size, 1)),
        median_ray_gap_m=float(np.median(pts.ray_gap[ok])) if ok.any() else float("nan"),
        seconds=dict(rectify=t1 - t0, match=t2 - t1, intersect=t3 - t2),
    )
    return TilePoints(pts.lon[ok], pts.lat[ok], pts.h[ok], score[ok], pts.ray_gap[ok], summary)


# ----------------------------------------------------------------------------- the workflow


def default_posting(gsd: float, crs) -> float:
    """Default DEM posting: twice the GSD (``gsd`` in metres), in the units of ``crs`` (for
    a geographic CRS, degrees of latitude: metres / 111 320 m)."""
    posting = float(f"{2.0 * gsd:.2g}")
    value = geodesy.metres_in_crs(posting, crs)
    return float(f"{value:.2g}") if CRS.from_user_input(crs).is_geographic else value


def check_lattice(bounds, posting: float):
    """:class:`InputError` when the DEM lattice of ``bounds`` at ``posting`` cannot be held:
    its cell sums (``len(SUM_LAYERS)`` float64 layers) exceed the available memory."""
    with np.errstate(over="ignore", invalid="ignore"):  # 5e-324: inf or NaN, refused below
        cols = np.float64(bounds[2] - bounds[0]) / posting
        rows = np.float64(bounds[3] - bounds[1]) / posting
        nbytes = 8.0 * len(SUM_LAYERS) * max(cols, 0) * max(rows, 0)
    check_allocation(
        nbytes,
        f"a DEM lattice of {cols:.3g} x {rows:.3g} cells at posting {posting:g} "
        "(choose a coarser --res)",
        fraction=0.5,
    )


def check_settings(settings) -> None:
    """:class:`InputError` naming the field for settings a library call could pass that the
    configuration file's checks (:func:`stereodem.config.load_config`) refuse: before,
    ``make_dem`` took them as they were and failed after the sparse matching with NumPy's or
    Python's own error (a dict or a string for a settings object: AttributeError; a tile
    size of 0: ZeroDivisionError; a posting given as text: UFuncTypeError) or pyproj's
    CRSError for an unknown output CRS."""
    parts = {
        "rectification": RectificationSettings,
        "matching": MatchingSettings,
        "refinement": RefinementSettings,
        "gridding": GriddingSettings,
    }
    if not isinstance(settings, StereoSettings):
        raise InputError(f"settings must be a StereoSettings, got {type(settings).__name__}")
    for name, kind in parts.items():
        if not isinstance(getattr(settings, name), kind):
            raise InputError(
                f"settings.{name} must be a {kind.__name__}, got "
                f"{type(getattr(settings, name)).__name__}"
            )
    tile = settings.rectification.tile_size
    if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or not 64 <= tile <= 16384:
        raise InputError(f"settings.rectification.tile_size must be 64..16384 px, got {tile!r}")
    if settings.matching.matcher not in MATCHERS:
        raise InputError(
            f"settings.matching.matcher must be one of {', '.join(MATCHERS)}, got "
            f"{settings.matching.matcher!r}"
        )
    res = settings.gridding.res
    number = isinstance(res, (int, float, np.number)) and not isinstance(res, bool)
    if res is not None and not (number and 0 < res < np.inf):
        raise InputError(
            f"settings.gridding.res must be a positive posting (CRS units), got {res!r}"
        )
    if settings.gridding.crs is not None:
        map_crs(settings.gridding.crs, "settings.gridding.crs")


def make_dem(
    left_image,
    right_image,
    left_model,
    right_model,
    settings: StereoSettings | None = None,
    *,
    seed_dem: DEM | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    runner: Callable | None = None,
    left_dtype=None,
    right_dtype=None,
    points_dir=None,
    pair_id: int = 0,
) -> DEMProducts:
    """Stereo DEM from two images and their sensor models.

    The inputs are checked first as ``stereodem dem`` checks them
    (:func:`stereodem.stereo.sanity.check_pair`: arrays vs models, seed DEM coverage and
    heights, stereo base, one radiometric scale), with the same one-line refusals; the
    findings and the base-to-height ratio go into ``info`` (``warnings``, ``status``,
    ``base_to_height``).

    Parameters
    ----------
    left_image, right_image : ndarray (rows, cols)
        The two images (any real dtype; memory maps are fine: tiles read only what they need).
    left_model, right_model : stereodem.sensor.models.base.SensorModel
        Their exact sensor models (image sizes must match the arrays).
    settings : StereoSettings, optional
    seed_dem : DEM, optional
        Coarse DEM giving each tile's height range (its heights under the tile +/- the margin).
    left_dtype, right_dtype : dtype, optional
        Bit depth of the images' files when the arrays were converted (default: the arrays'
        dtypes); different ones put the right image on the left's radiometric scale.
    progress : callable, optional
        Called as ``progress(done, total, tile_summary)`` after each tile (serial run).
    runner : callable, optional
        ``runner(process_tile, tiles, inputs, settings) -> iterable of TileResult`` runs the
        tiles elsewhere (process pool, Dask: :func:`stereodem.stereo.execution.tile_runner`); it
        may drop failed tiles. Results must come back in
        :func:`~stereodem.stereo.tiling.tile_order` so the output is independent of the
        runner; they are taken one at a time as they come (a generator need hold only one,
        and its tiles' sums are added while it runs the next ones).
    points_dir : path, optional
        Each tile also writes its points to ``points_<index>.npz`` there
        (:func:`stereodem.stereo.pointcloud.write_las` merges them).
    pair_id : int
        The points' ``source_pair`` (an N-view job's pair id; 0 for a pair job).

    Returns
    -------
    DEMProducts

    Raises
    ------
    NoOverlapError
        The two images see no common ground at any height of the range.
    InputError
        Unusable height range, or image arrays that do not match the models.
    SparseMatchError
        No height range or seed DEM given, and too few sparse matches to find the heights.
    """
    settings = settings or StereoSettings()
    check_settings(settings)
    seed = as_dem(seed_dem) if seed_dem is not None else None
    checked = check_pair(
        left_image,
        right_image,
        left_model,
        right_model,
        settings.rectification.height_range,
        seed,
        left_dtype,
        right_dtype,
    )
    products = dem_of_checked_pair(
        checked.left,
        checked.right,
        left_model,
        right_model,
        settings,
        seed_dem=seed,
        progress=progress,
        runner=runner,
        points_dir=points_dir,
        pair_id=pair_id,
    )
    return checked.report(products)


def dem_of_checked_pair(
    left_image,
    right_image,
    left_model,
    right_model,
    settings: StereoSettings,
    *,
    seed_dem: DEM | None = None,
    progress=None,
    runner=None,
    points_dir=None,
    pair_id: int = 0,
) -> DEMProducts:
    """:func:`make_dem` after :func:`~stereodem.stereo.sanity.check_pair` (for callers that
    make several DEMs of one checked pair, as the jitter correction does)."""
    rect, gs = settings.rectification, settings.gridding
    t_start = time.perf_counter()
    # 1. height range
    seed = as_dem(seed_dem) if seed_dem is not None else None
    sparse = _sparse_stage(left_image, right_image, left_model, right_model, rect, seed)
    seed_margin = None
    if sparse is not None:
        right_model = sparse.right_model
        if sparse.terrain is not None:
            seed, seed_margin = sparse.terrain.seed_dem, sparse.terrain.tile_margin
            rect = dataclasses.replace(rect, height_range=sparse.height_range)
    height_range = pair_height_range(left_model, right_model, rect, seed)
    gsd = left_model.gsd(0.5 * sum(height_range))
    max_gap = gs.max_ray_gap if gs.max_ray_gap is not None else 2.0 * gsd
    crs = gs.crs
    if crs is None:
        clon, clat = left_model.center_lonlat(0.5 * sum(height_range))
        crs = geodesy.utm_crs(clon, clat)
    posting = gs.res or default_posting(gsd, crs)
    # 2. overlap, tiles and the output lattice
    tiles = plan_tiles(left_model, right_model, rect, height_range)
    log.info(
        "stereo DEM: %d tile(s) of ~%d px, heights %.0f..%.0f m, matcher %s, posting %s",
        len(tiles),
        rect.tile_size,
        height_range[0],
        height_range[1],
        settings.matching.matcher,
        posting_text(float(f"{posting:.3g}"), crs_unit(crs)),
    )
    bounds = gs.bounds
    if bounds is None:
        bounds = footprint_bounds(left_model, tiles, height_range, posting, crs)
    check_lattice(bounds, posting)
    spec = GridSpec.from_bounds(
        bounds, posting, crs, method=gs.method, sigma=gs.gaussian_sigma, geoid=gs.geoid
    )
    inputs = PairInputs(
        left_image,
        right_image,
        left_model,
        right_model,
        height_range,
        seed,
        max_gap,
        spec,
        seed_margin,
        points_dir=str(points_dir) if points_dir is not None else None,
        pair_id=int(pair_id),
    )
    # 3. tiles: here, one after the other, or through the caller's runner (pool, Dask), in
    # tile_order (largest first): the order their sums are added in, whatever runs them
    n_failed = len(getattr(runner, "failures", ()))  # the failures of the runner's earlier calls
    if runner is None:

        def serial():
            for k, tile in enumerate(tile_order(tiles), start=1):
                res = process_tile(tile, inputs, settings)
                if progress is not None:
                    progress(k, len(tiles), res.summary)
                yield res

        results = serial()
    else:
        results = runner(process_tile, tiles, inputs, settings)
    # 4. grid: the tiles' cell sums, added in tile_order (independent of the runner) as they
    # come, keeping only each tile's QA summary
    total = np.zeros((len(SUM_LAYERS),) + tuple(spec.shape))
    summaries, n_points = [], 0
    with contextlib.closing(results) if hasattr(results, "close") else contextlib.nullcontext():
        for res in results:  # an error here closes a runner's generator: its pool stops
            s = res.summary
            log.info(
                "tile %s: y-parallax RMS %.3f px, disparity %.0f..%.0f px, %d points",
                s["tile"],
                s["residual_rms_px"],
                *s["disparity_range"],
                s["n_points"],
            )
            res.cells.add_to(total)
            n_points += int(res.cells.n_points)
            summaries.append(s)
            res = None
    # the summaries in tile (index) order, as the tiles were planned
    position = {tuple(t.bounds): k for k, t in enumerate(tiles)}
    summaries.sort(key=lambda s: position.get(tuple(s["tile"]), len(tiles)))
    if n_points == 0 and gs.bounds is None:
        failed = getattr(runner, "failures", ())[n_failed:]
        raise no_point_matched(tiles, settings, failed, summaries, max_gap)
    dem = finish(spec, total, crop=gs.bounds is None)
    del total
    seconds = time.perf_counter() - t_start
    rms = [s["residual_rms_px"] for s in summaries]
    pileup = _pileup(summaries, n_points)
    info = StereoInfo(
        height_range=list(height_range),
        gsd_m=gsd,
        posting=posting,
        max_ray_gap_m=max_gap,
        n_tiles=len(tiles),
        max_residual_rms_px=float(max(rms)) if rms else float("nan"),
        valid_cells=float(np.isfinite(dem.heights).mean()),
        pointing=(
            sparse.pointing.summary()
            if sparse is not None and sparse.pointing is not None
            else dict(kind="none")
        ),
        sparse=sparse.summary() if sparse is not None else None,
        height_source=(
            "sparse matches"
            if sparse is not None and sparse.terrain is not None
            else "seed DEM"
            if seed is not None
            else "height range"
            if rect.height_range is not None
            else "model validity range"
        ),
        height_pileup=pileup,
        suspect=pileup["suspect"],
        # a range from the sparse matches, a seed DEM or the settings is widened by it
        # (stereo.plan.pair_height_range); the models' validity range is not
        height_margin_m=(
            float(rect.height_margin) if seed is not None or rect.height_range is not None else 0.0
        ),
    )
    log.info(
        "stereo DEM: %d points gridded to %dx%d cells in %.1f s",
        n_points,
        dem.grid.width,
        dem.grid.height,
        seconds,
    )
    return DEMProducts(dem, summaries, n_points, seconds, settings.summary(), info)


# ----------------------------------------------------------------------------- helpers


def _sparse_stage(left_image, right_image, left_model, right_model, rect, seed):
    """Run :func:`run_sparse_stage` when the run needs it (relative pointing, or heights when
    no height range or seed DEM is given); None when it is not needed or, for the pointing
    alone, when it finds too few matches (a warning is logged)."""
    auto = rect.height_range is None and seed is None and rect.auto_heights
    if not (auto or rect.pointing_correction):
        return None
    lo, hi = pair_height_bounds(left_model, right_model)
    given = rect.height_range is not None or seed is not None
    check_range = pair_height_range(left_model, right_model, rect, seed) if given else None
    # overlap at any height of the search range first: a clear NoOverlapError, not "no match"
    overlap_window(
        left_model,
        right_model,
        np.linspace(*(check_range or (lo, hi)), 5),
        step=max(8, min(left_model.width, left_model.height) // 16),
    )
    try:
        return run_sparse_stage(
            left_image,
            right_image,
            left_model,
            right_model,
            heights=auto,
            pointing=rect.pointing_correction,
            height_range=check_range,
            reference_dem=seed if rect.pointing_uses_seed else None,
            **rect.sparse_options,
        )
    except SparseMatchError as exc:
        if auto:
            raise SparseMatchError(
                f"{exc}; give a height range (--height-range) or a seed DEM (--seed-dem)"
            ) from None
        log.warning("%s: no relative pointing correction", exc)
        return None


def _pileup(summaries, n_points, *, max_share: float = 0.05) -> dict:
    """Share of the points whose height lies at a bound of its tile's search range (the
    matcher hit the end of the range: wrong heights or an uncorrected pointing error);
    ``summaries`` are the tiles' QA summaries."""
    low = sum(s.get("n_at_low_bound", 0) for s in summaries)
    high = sum(s.get("n_at_high_bound", 0) for s in summaries)
    n = max(n_points, 1)
    out = dict(low_share=low / n, high_share=high / n, suspect=bool(max(low, high) / n > max_share))
    if out["suspect"]:
        log.warning(
            "suspect DEM: %.1f%% of the heights lie at the lower and %.1f%% at the upper "
            "bound of their search range (a wrong height range, seed DEM or pointing?)",
            100 * out["low_share"],
            100 * out["high_share"],
        )
    return out
