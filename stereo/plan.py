"""Planning a stereo run: the height range, the overlap of the two images, the tiles of the
left image and the ground extent they can see.
"""

from __future__ import annotations

import logging

import numpy as np

from stereodem.core import geodesy
from stereodem.core.dem import as_dem
from stereodem.core.errors import InputError, NoOverlapError, SensorModelError
from stereodem.sensor.models.base import pair_height_bounds

from .settings import RectificationSettings
from .tiling import Tile, renumber, tile_grid

log = logging.getLogger(__name__)

__all__ = [
    "scene_lonlat",
    "seed_height_range",
    "pair_height_range",
    "overlap_window",
    "plan_tiles",
    "footprint_bounds",
    "tile_height_range",
    "base_to_height",
]


def scene_lonlat(left, right):
    """Ground points (lon, lat in degrees) of the left image's footprint: its border
    (:meth:`~stereodem.sensor.models.base.SensorModel.footprint`) at both ends of the pair's
    validity range (:func:`~stereodem.sensor.models.base.pair_height_bounds`, within
    -500..9000 m)."""
    lo, hi = pair_height_bounds(left, right)
    lo, hi = max(min(lo, hi), -500.0), min(max(lo, hi), 9000.0)
    with np.errstate(invalid="ignore"):
        outlines = [left.footprint(h) for h in (lo, hi)]
    return tuple(np.concatenate([np.asarray(o[k], float) for o in outlines]) for k in (0, 1))


def seed_height_range(seed_dem, left, right) -> tuple[float, float]:
    """(min, max) ellipsoidal heights (m) of the seed DEM under the scene (:func:`scene_lonlat`),
    not of the whole file: a seed DEM may span far more than the scene (a 1 degree SRTM tile
    around a Pleiades scene), and its heights elsewhere say nothing of this terrain.
    :class:`~stereodem.core.errors.DEMCoverageError` when no valid height lies under it."""
    return as_dem(seed_dem).height_range(around=scene_lonlat(left, right))


def pair_height_range(left, right, settings: RectificationSettings, seed_dem=None):
    """Global height range (m, ellipsoidal) of a run, margin included.

    Raises :class:`InputError` when the range is unusable (non-finite, inverted, or outside
    the models' validity ranges).
    """
    lo, hi = pair_height_bounds(left, right)
    if settings.height_range is not None:
        try:
            hmin, hmax = (float(v) for v in settings.height_range)
        except (TypeError, ValueError):
            raise InputError(
                f"height range {settings.height_range!r}: expected two numbers"
            ) from None
        if not (np.isfinite(hmin) and np.isfinite(hmax)) or hmax < hmin:
            raise InputError(
                f"height range {hmin:g}..{hmax:g} m is unusable (need finite MIN <= MAX)"
            )
        hmin, hmax = hmin - settings.height_margin, hmax + settings.height_margin
    elif seed_dem is not None:
        hmin, hmax = seed_height_range(seed_dem, left, right)
        hmin, hmax = hmin - settings.height_margin, hmax + settings.height_margin
    else:
        hmin, hmax = lo, hi
        log.warning(
            "no height range or seed DEM given: searching the models' whole height "
            "range %.0f..%.0f m (slow, more blunders)",
            hmin,
            hmax,
        )
    if hmax < lo or hmin > hi:
        raise InputError(
            f"height range {hmin:g}..{hmax:g} m lies outside the sensor models' "
            f"validity range {lo:g}..{hi:g} m"
        )
    return max(hmin, lo), min(hmax, hi)


def overlap_window(left, right, heights, *, step: int = 64):
    """Part of the left image that sees ground also seen by the right image.

    Left pixels on a grid (spacing ``step``) are localised at each of ``heights`` (one height
    or several spanning the search range) and projected into the right image; a pixel counts
    when it lands inside the right image at any of them. Returns ``(window, inside)``: the
    bounding box ``(col0, row0, col1, row1)`` of those left pixels (widened by one grid step),
    and a function ``inside(tile) -> bool`` telling whether a tile holds any of them. Raises
    :class:`NoOverlapError` when no pixel does.
    """
    heights = np.atleast_1d(np.asarray(heights, float))
    w, h = left.width, left.height
    cs = np.unique(np.concatenate([np.arange(0, w, step), [w - 1]])).astype(float)
    rs = np.unique(np.concatenate([np.arange(0, h, step), [h - 1]])).astype(float)
    cc, rr = np.meshgrid(cs, rs)
    ok = np.zeros(cc.size, bool)
    for height in heights:
        hh = np.full(cc.size, float(height))
        with np.errstate(invalid="ignore"):
            lon, lat = left.localize(cc.ravel(), rr.ravel(), hh)
            c2, r2 = right.project(lon, lat, hh)
            ok |= (
                (c2 >= -0.5) & (c2 <= right.width - 0.5) & (r2 >= -0.5) & (r2 <= right.height - 0.5)
            )
    if not ok.any():
        at = (
            f"at {heights[0]:.0f} m"
            if heights.size == 1
            else f"at any height {heights.min():.0f}..{heights.max():.0f} m"
        )
        raise NoOverlapError(
            f"the two images do not overlap (no left pixel, localised {at}, "
            f"projects into the right image)"
        )
    pc, pr = cc.ravel()[ok], rr.ravel()[ok]
    window = (
        max(pc.min() - step, 0),
        max(pr.min() - step, 0),
        min(pc.max() + step, w - 1),
        min(pr.max() + step, h - 1),
    )

    def inside(tile: Tile) -> bool:
        c0, r0, c1, r1 = tile.bounds
        return bool(
            np.any((pc >= c0 - step) & (pc <= c1 + step) & (pr >= r0 - step) & (pr <= r1 + step))
        )

    return tuple(int(v) for v in window), inside


def plan_tiles(left, right, settings: RectificationSettings, height_range, *, n_heights: int = 5):
    """Tiles of the left image that overlap the right image at some height of the range
    (``n_heights`` heights spanning it)."""
    heights = np.linspace(height_range[0], height_range[1], n_heights)
    window, inside = overlap_window(left, right, heights, step=max(8, settings.tile_size // 8))
    tiles = tile_grid(left.width, left.height, settings.tile_size, window=window)
    return renumber([t for t in tiles if inside(t)])


def footprint_bounds(left, tiles, height_range, posting, crs, *, samples: int = 9):
    """Map extent (xmin, ymin, xmax, ymax; multiples of ``posting``) of the ground the tiles
    can see: each tile's outline (``samples`` points per edge) localised by the left model at
    both ends of the height range and projected to ``crs``, plus two cells of margin.
    """
    if not tiles:
        raise NoOverlapError("no tile of the left image overlaps the right image")
    t = np.linspace(0.0, 1.0, samples)
    cs, rs = [], []
    for tile in tiles:
        c0, r0, c1, r1 = tile.bounds
        cs.append(
            np.concatenate(
                [c0 + (c1 - c0) * t, np.full(samples, c1), c1 - (c1 - c0) * t, np.full(samples, c0)]
            )
        )
        rs.append(
            np.concatenate(
                [np.full(samples, r0), r0 + (r1 - r0) * t, np.full(samples, r1), r1 - (r1 - r0) * t]
            )
        )
    c, r = np.concatenate(cs), np.concatenate(rs)
    xs, ys = [], []
    for hh in height_range:
        lon, lat = left.localize(c, r, np.full(c.size, float(hh)))
        x, y = geodesy.lonlat_to_crs(lon, lat, crs)
        xs.append(np.asarray(x, float))
        ys.append(np.asarray(y, float))
    x, y = np.concatenate(xs), np.concatenate(ys)
    if not (np.isfinite(x).any() and np.isfinite(y).any()):
        raise NoOverlapError("the left image's footprint does not map into the output CRS")
    pad = 2 * posting
    return (
        np.floor((np.nanmin(x) - pad) / posting) * posting,
        np.floor((np.nanmin(y) - pad) / posting) * posting,
        np.ceil((np.nanmax(x) + pad) / posting) * posting,
        np.ceil((np.nanmax(y) + pad) / posting) * posting,
    )


def tile_height_range(tile: Tile, inputs, margin: float):
    """Height range (m) of a tile: the seed DEM under it +/- ``margin`` (or the seed's own
    ``inputs.seed_margin`` when set, e.g. the sparse-match surface's), else the global range."""
    margin = getattr(inputs, "seed_margin", None) or margin
    if inputs.seed_dem is None:
        return inputs.height_range
    c0, r0, c1, r1 = tile.bounds
    cc, rr = np.meshgrid(np.linspace(c0, c1, 9), np.linspace(r0, r1, 9))
    loc = inputs.left_model.localize_dem(
        cc.ravel(), rr.ravel(), inputs.seed_dem, h0=0.5 * sum(inputs.height_range)
    )
    hs = loc.h[np.isfinite(loc.h)]
    if hs.size < 0.5 * cc.size:
        return inputs.height_range
    lo, hi = inputs.height_range
    return (max(lo, float(hs.min()) - margin), min(hi, float(hs.max()) + margin))


def base_to_height(left, right, h0: float, *, dh: float = 100.0, n: int = 5) -> float:
    """Base-to-height ratio of a pair, from the models: the median over an ``n`` x ``n`` grid
    of left pixels of the ground separation of the two rays ``dh`` metres above their
    intersection at height ``h0``, divided by ``dh``.

    A ground point at ``h0`` seen by a left pixel is projected into the right image; both
    pixels are localised at ``h0 + dh``: the two ground points are B/H x dh apart.
    """
    cs = np.linspace(0, left.width - 1, n)
    rs = np.linspace(0, left.height - 1, n)
    c, r = (a.ravel() for a in np.meshgrid(cs, rs))
    h = np.full(c.size, float(h0))
    lon, lat = left.localize(c, r, h)
    ok = np.isfinite(lon) & np.isfinite(lat)  # pixels beyond the horizon localise nowhere
    if not ok.any():
        raise SensorModelError(
            f"the left image's sensor model localises none of its pixels on the Earth (at "
            f"{h0:.0f} m): the model or its sidecar is wrong"
        )
    c, r, h, lon, lat = c[ok], r[ok], h[ok], lon[ok], lat[ok]
    c2, r2 = (np.asarray(a, float) for a in right.project(lon, lat, h))
    ok = np.isfinite(c2) & np.isfinite(r2)
    if not ok.any():
        raise SensorModelError(
            "the right image's sensor model sees none of the ground the left image sees: "
            "the model or its sidecar is wrong"
        )
    c, r, h, c2, r2 = c[ok], r[ok], h[ok], c2[ok], r2[ok]
    up = h + dh
    lon_l, lat_l = left.localize(c, r, up)
    lon_r, lat_r = right.localize(c2, r2, up)
    pl = np.stack(geodesy.geodetic_to_ecef(lon_l, lat_l, up))
    pr = np.stack(geodesy.geodetic_to_ecef(lon_r, lat_r, up))
    sep = np.linalg.norm(pl - pr, axis=0)
    sep = sep[np.isfinite(sep)]
    if not sep.size:
        raise InputError(
            "cannot measure the base of the pair: the models do not localise the left image"
        )
    return float(np.median(sep) / dh)
