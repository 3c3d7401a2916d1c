"""Terrain heights from sparse matches: a robust height range and a coarse seed surface.

The sparse matches of :func:`stereodem.stereo.sparse.sparse_matches` are intersected through
the two models (:func:`stereodem.sensor.geo.intersect.intersect_matches`; give the right model
corrected by :func:`stereodem.stereo.pointing.relative_pointing` when the pair has a pointing
error). Blunders are rejected twice: by the ray gap (lines of sight that miss each other by
much more than the others), and by the height difference to the median of the nearest
neighbouring points (a match on the wrong texture lands above or below its neighbours). The
remaining heights give

* the **height range** of the scene: the kept points' lowest and highest heights (blunders
  are already out; sparse matches under-sample peaks and gorges, so no percentile is cut
  off) widened by ``margin`` (default 10 % of the span or ``tile_margin``, whichever is
  larger, at least ``min_margin``), as CARS derives its disparity range from its sparse
  matches;
* a **seed surface**: the mean height of the points in cells of a coarse map grid (UTM of
  the scene centre, posting set so that cells hold a few points each), empty cells filled by
  normalised Gaussian convolution of the filled ones (widening until all are filled), as a
  :class:`stereodem.core.dem.DEM` (ellipsoidal heights). ``tile_margin`` is how far the
  points stray from that surface (99th percentile, plus ``min_margin``): the margin with which
  the surface sets each tile's height range.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from affine import Affine
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from stereodem.core import geodesy
from stereodem.core.dem import DEM, ELLIPSOID
from stereodem.core.stats import nmad as _nmad
from stereodem.sensor.geo.intersect import intersect_matches
from stereodem.sensor.models.base import pair_height_bounds

from .sparse import SparseMatchError, SparseMatches

log = logging.getLogger(__name__)

__all__ = ["TerrainHeights", "terrain_heights", "tile_height_range"]


@dataclass
class TerrainHeights:
    """Result of :func:`terrain_heights`.

    Attributes
    ----------
    height_range : (float, float)
        Robust height range of the scene, margin included (m above the WGS84 ellipsoid).
    seed_dem : DEM
        Coarse surface of the points (ellipsoidal heights, UTM).
    tile_margin : float
        Margin (m) to put around the seed surface's heights under a tile.
    n_points, n_rejected : int
        Points kept and rejected as blunders.
    lon, lat, h : ndarray
        The kept points (degrees, degrees, metres).
    info : dict
        Percentiles, ray-gap threshold, grid posting.
    """

    height_range: tuple
    seed_dem: DEM
    tile_margin: float
    n_points: int
    n_rejected: int
    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Plain-dict record for reports (JSON-serialisable)."""
        return dict(
            height_range_m=[float(v) for v in self.height_range],
            tile_margin_m=float(self.tile_margin),
            n_points=self.n_points,
            n_rejected=self.n_rejected,
            seed_shape=list(self.seed_dem.shape),
            **self.info,
        )


def _neighbour_deviation(x, y, h, k):
    """Height minus the median height of the ``k`` nearest other points (NaN when too few)."""
    k = min(k, len(h) - 1)
    if k < 3:
        return np.full(len(h), np.nan)
    _, idx = cKDTree(np.stack([x, y], -1)).query(np.stack([x, y], -1), k=k + 1)
    return h - np.median(h[idx[:, 1:]], axis=1)


def _fill_empty(grid):
    """Empty (NaN) cells filled by normalised Gaussian convolution of the filled ones, the
    width doubling (1, 2, 4, ... cells) until every cell has a value: a smooth continuation
    of the surface into the gaps and beyond the points' hull (no triangulation)."""
    have = np.isfinite(grid)
    out = grid.copy()
    values = np.where(have, grid, 0.0)
    sigma = 1.0
    while not np.isfinite(out).all():
        w = gaussian_filter(have.astype(float), sigma, mode="constant")
        v = gaussian_filter(values, sigma, mode="constant")
        todo = ~np.isfinite(out) & (w > 1e-6)
        out[todo] = v[todo] / w[todo]
        sigma *= 2.0
    return out


def terrain_heights(
    matches: SparseMatches,
    left,
    right,
    *,
    margin: float | None = None,
    min_margin: float = 30.0,
    min_points: int = 20,
    points_per_cell: int = 4,
    posting: float | None = None,
    crs=None,
) -> TerrainHeights:
    """Robust height range and coarse seed surface from sparse matches.

    Parameters
    ----------
    matches : SparseMatches
    left, right : SensorModel
        Models to intersect with (the right one corrected for pointing, preferably).
    margin : float, optional
        Metres added on both sides of the points' range; default max(10 % of the span,
        ``tile_margin``, ``min_margin``).
    min_margin : float
        Smallest margin (m) of the range and of ``tile_margin``.
    min_points : int
        Fewer surviving points raise :class:`SparseMatchError`.
    points_per_cell : int
        Target number of points per seed-surface cell (sets the posting).
    posting : float, optional
        Seed-surface posting in metres (overrides ``points_per_cell``).
    crs : optional
        Seed-surface CRS; default the UTM zone of the points' centre.

    Returns
    -------
    TerrainHeights
    """
    n0 = len(matches)
    if n0 < min_points:
        raise SparseMatchError(
            f"terrain heights: only {n0} sparse match(es) agree with the "
            f"models (need >= {min_points}); give a height range or a seed DEM"
        )
    inter = intersect_matches(left, right, matches.col1, matches.row1, matches.col2, matches.row2)
    h, gap = inter.h, inter.ray_gap
    lo_b, hi_b = pair_height_bounds(left, right)
    ok = np.isfinite(h) & np.isfinite(gap)
    span_b = hi_b - lo_b
    ok &= (h >= lo_b - 0.5 * span_b) & (h <= hi_b + 0.5 * span_b)
    if ok.sum() < min_points:
        raise SparseMatchError(
            f"terrain heights: only {int(ok.sum())} sparse match(es) intersect "
            f"(need >= {min_points}); give a height range or a seed DEM"
        )
    gap_lim = float(np.median(gap[ok]) + 5.0 * _nmad(gap[ok]) + 1e-3)
    ok &= gap <= gap_lim
    lon, lat = inter.lon, inter.lat
    centre = (float(np.median(lon[ok])), float(np.median(lat[ok])))
    crs = geodesy.utm_crs(*centre) if crs is None else crs
    x, y = (np.asarray(a, float) for a in geodesy.lonlat_to_crs(lon, lat, crs))
    idx = np.nonzero(ok)[0]
    # precision floor of a height: the ray gap is the same order as the height error
    floor = max(3.0 * float(np.median(gap[ok])), 1.0)
    dev = _neighbour_deviation(x[idx], y[idx], h[idx], 8)
    bad = np.abs(dev) > max(4.0 * _nmad(dev), floor)
    ok[idx[bad]] = False
    dev_kept = np.abs(dev[~bad])
    n = int(ok.sum())
    if n < min_points:
        raise SparseMatchError(
            f"terrain heights: only {n} consistent point(s) from the sparse "
            f"matches (need >= {min_points}); give a height range or a seed DEM"
        )
    hk, xk, yk = h[ok], x[ok], y[ok]
    p_lo, p_hi = float(hk.min()), float(hk.max())
    span = float(p_hi - p_lo)
    m = max(0.1 * span, min_margin) if margin is None else float(margin)
    height_range = (float(p_lo - m), float(p_hi + m))

    # coarse seed surface
    xmin, xmax, ymin, ymax = xk.min(), xk.max(), yk.min(), yk.max()
    area = max((xmax - xmin) * (ymax - ymin), 1.0)
    if posting is None:
        posting = float(np.sqrt(area * points_per_cell / n))
    posting = max(float(posting), 1e-6)
    x0, y1 = xmin - posting, ymax + posting
    cols = int(np.ceil((xmax + posting - x0) / posting)) + 1
    rows = int(np.ceil((y1 - (ymin - posting)) / posting)) + 1
    ci = np.clip(((xk - x0) / posting).astype(int), 0, cols - 1)
    ri = np.clip(((y1 - yk) / posting).astype(int), 0, rows - 1)
    flat = ri * cols + ci
    sums = np.bincount(flat, hk, rows * cols)
    counts = np.bincount(flat, minlength=rows * cols)
    grid = np.full(rows * cols, np.nan)
    grid[counts > 0] = sums[counts > 0] / counts[counts > 0]
    grid = grid.reshape(rows, cols)
    grid = _fill_empty(grid)
    transform = Affine(posting, 0.0, x0, 0.0, -posting, y1)
    seed = DEM(grid.astype(np.float32), transform, crs, ELLIPSOID, "sparse-match seed surface")
    # how far the terrain strays from the surface between points: the larger of the points'
    # departures from the surface and from their neighbours (a leave-one-out estimate of the
    # interpolation error at the points' spacing), both at their 99th percentile
    on_seed = np.abs(hk - seed.sample(lon[ok], lat[ok], reference=ELLIPSOID))
    strays = [np.nanpercentile(a, 99) for a in (on_seed, dev_kept) if np.isfinite(a).any()]
    tile_margin = float(max(strays, default=m) + min_margin)
    if margin is None and tile_margin > m:
        # peaks and gorges between the points stray from them by up to about tile_margin:
        # the global range keeps at least that much room
        m = tile_margin
        height_range = (float(p_lo - m), float(p_hi + m))
    info = dict(
        heights_m={
            "min": p_lo,
            "p1": float(np.percentile(hk, 1)),
            "p50": float(np.median(hk)),
            "p99": float(np.percentile(hk, 99)),
            "max": p_hi,
        },
        ray_gap_limit_m=gap_lim,
        ray_gap_median_m=float(np.median(gap[ok])),
        seed_posting_m=posting,
        margin_m=m,
    )
    log.info(
        "terrain heights from %d sparse points (%d rejected): %.0f..%.0f m "
        "(min..max, median %.0f m), height range with margin %.0f..%.0f m; seed "
        "surface %dx%d at %.0f m, tile margin %.0f m",
        n,
        n0 - n,
        p_lo,
        p_hi,
        np.median(hk),
        height_range[0],
        height_range[1],
        rows,
        cols,
        posting,
        tile_margin,
    )
    return TerrainHeights(height_range, seed, tile_margin, n, n0 - n, lon[ok], lat[ok], hk, info)


def tile_height_range(model, bounds, terrain: TerrainHeights, *, samples: int = 9):
    """Height range (m) of an image window from the seed surface.

    The window ``(col0, row0, col1, row1)`` of ``model``'s image is sampled on a
    ``samples`` x ``samples`` grid, localised on ``terrain.seed_dem``; the range is the
    sampled heights' span widened by ``terrain.tile_margin`` and clipped to
    ``terrain.height_range``. The global range is returned when fewer than half the samples
    land on the surface.
    """
    c0, r0, c1, r1 = bounds
    cc, rr = np.meshgrid(np.linspace(c0, c1, samples), np.linspace(r0, r1, samples))
    lo, hi = terrain.height_range
    loc = model.localize_dem(cc.ravel(), rr.ravel(), terrain.seed_dem, h0=0.5 * (lo + hi))
    hs = loc.h[np.isfinite(loc.h)]
    if hs.size < 0.5 * cc.size:
        return terrain.height_range
    return (
        max(lo, float(hs.min()) - terrain.tile_margin),
        min(hi, float(hs.max()) + terrain.tile_margin),
    )
