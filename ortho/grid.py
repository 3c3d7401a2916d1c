"""Output map grids for orthoimages: a north-up raster in a projected CRS.

The grid of an orthoimage is chosen from the sensor model and the DEM: the CRS is the UTM zone
of the image centre unless one is given, the posting is the image's ground sample distance
(:meth:`stereodem.sensor.models.base.SensorModel.gsd`) unless given, and the bounds enclose the image footprint
localised at the lowest and highest DEM heights under it, snapped outward to multiples of the
posting.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from affine import Affine
from pyproj import CRS

from stereodem.sensor.geo import geodesy
from stereodem.sensor.errors import CRSError, DEMCoverageError, InputError


@dataclass(frozen=True)
class MapGrid:
    """A north-up raster grid.

    Attributes
    ----------
    transform : affine.Affine
        GDAL pixel-corner transform (map x = east, y = north, metres for projected CRSs).
    width, height : int
        Number of columns and rows.
    crs : pyproj.CRS
        Map CRS.
    """

    transform: Affine
    width: int
    height: int
    crs: CRS

    def __post_init__(self):
        object.__setattr__(self, "crs", CRS.from_user_input(self.crs))
        t = self.transform
        if abs(t.b) > 0 or abs(t.d) > 0 or t.a <= 0 or t.e >= 0:
            raise InputError(f"MapGrid: the transform must be north-up (got {tuple(t)[:6]})")
        if self.width < 1 or self.height < 1:
            raise InputError(f"MapGrid: empty grid {self.width} x {self.height}")

    @property
    def shape(self):
        """(rows, cols)."""
        return (self.height, self.width)

    @property
    def res(self):
        """(x posting, y posting), map units (positive)."""
        return (self.transform.a, -self.transform.e)

    @property
    def bounds(self):
        """(west, south, east, north) of the cell edges, map units."""
        t = self.transform
        return (t.c, t.f + t.e * self.height, t.c + t.a * self.width, t.f)

    def xy(self, cols, rows):
        """Map coordinates of cell centres at (fractional) grid ``cols, rows`` (0 = first centre)."""
        t = self.transform
        return (t.c + t.a * (np.asarray(cols, float) + 0.5),
                t.f + t.e * (np.asarray(rows, float) + 0.5))

    def colrow(self, x, y):
        """Fractional grid (col, row) of map points, cell centres at integers."""
        t = self.transform
        return ((np.asarray(x, float) - t.c) / t.a - 0.5, (np.asarray(y, float) - t.f) / t.e - 0.5)

    def lonlat(self, cols, rows):
        """Longitude/latitude (deg) of cell centres."""
        return geodesy.crs_to_lonlat(*self.xy(cols, rows), self.crs)

    def window(self, row0: int, row1: int) -> "MapGrid":
        """The sub-grid of rows ``row0:row1``."""
        return MapGrid(self.transform @ Affine.translation(0, row0), self.width, row1 - row0, self.crs)


def _nice_posting(gsd: float) -> float:
    """The GSD rounded to three significant digits (a readable posting)."""
    return float(f"{gsd:.3g}")


def grid_from_bounds(bounds, res, crs) -> MapGrid:
    """A grid covering ``bounds`` (west, south, east, north) with posting ``res``, snapped outward
    to multiples of ``res`` (so that grids of the same posting align)."""
    res = float(res)
    if not np.isfinite(res) or res <= 0:
        raise InputError(f"grid posting must be positive, got {res}")
    w, s, e, n = (float(v) for v in bounds)
    if not all(np.isfinite([w, s, e, n])) or e <= w or n <= s:
        raise InputError(f"empty or invalid grid bounds {bounds}")
    x0, y1 = np.floor(w / res) * res, np.ceil(n / res) * res
    x1, y0 = np.ceil(e / res) * res, np.floor(s / res) * res
    width, height = int(round((x1 - x0) / res)), int(round((y1 - y0) / res))
    return MapGrid(Affine(res, 0.0, x0, 0.0, -res, y1), max(width, 1), max(height, 1), crs)


def footprint_height_range(model, dem, *, samples: int = 41):
    """(min, max) ellipsoidal DEM height (m) under the image footprint.

    The footprint is localised at the DEM's mean height, its bounding box sampled on a
    ``samples x samples`` lattice; raises :class:`DEMCoverageError` if the DEM has no valid
    height there.
    """
    step = max(1, int(np.sqrt(dem.heights.size / 1e5)))
    h0 = float(np.nanmedian(dem.heights[::step, ::step]))     # first guess, any vertical datum
    lon, lat = model.footprint(h0)
    for _ in range(2):
        lo_, la_ = np.meshgrid(np.linspace(np.nanmin(lon), np.nanmax(lon), samples),
                               np.linspace(np.nanmin(lat), np.nanmax(lat), samples))
        z = dem.sample(lo_, la_)
        if not np.isfinite(z).any():
            raise DEMCoverageError(
                f"{dem.path or 'DEM'}: no valid height under the image footprint lon "
                f"{np.nanmin(lon):.5f}..{np.nanmax(lon):.5f}, lat {np.nanmin(lat):.5f}..{np.nanmax(lat):.5f} "
                f"(DEM extent lon/lat {tuple(round(v, 5) for v in dem.bounds_lonlat())})")
        h_lo, h_hi = float(np.nanmin(z)), float(np.nanmax(z))
        lon1, lat1 = model.footprint(h_lo)
        lon2, lat2 = model.footprint(h_hi)
        lon, lat = np.concatenate([lon1, lon2]), np.concatenate([lat1, lat2])
    return h_lo, h_hi


def grid_for_model(model, dem, *, res: float | None = None, crs=None, h_range=None) -> MapGrid:
    """The map grid of an orthoimage of ``model``'s image over ``dem``.

    Parameters
    ----------
    model : stereodem.sensor.models.base.SensorModel
    dem : stereodem.sensor.geo.dem.DEM
        Used for the height range under the footprint (ellipsoidal).
    res : float, optional
        Posting in map units (m); default: the image GSD at the mean terrain height, to three
        significant digits.
    crs : CRS-like, optional
        Map CRS (projected); default the UTM zone of the image centre.
    h_range : (float, float), optional
        Ellipsoidal height range to localise the footprint at (default from the DEM).
    """
    h_lo, h_hi = h_range if h_range is not None else footprint_height_range(model, dem)
    if crs is None:
        crs = geodesy.utm_crs(*model.center_lonlat(0.5 * (h_lo + h_hi)))
    crs = CRS.from_user_input(crs)
    if crs.is_geographic:
        raise CRSError(f"the orthoimage CRS must be projected (metres), got {crs.to_string()}")
    if res is None:
        res = _nice_posting(model.gsd(0.5 * (h_lo + h_hi)))
    xs, ys = [], []
    for h in (h_lo, h_hi):
        lon, lat = model.footprint(h, n=21)
        x, y = geodesy.lonlat_to_crs(lon, lat, crs)
        xs.append(x)
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise CRSError(f"the image footprint cannot be expressed in {crs.to_string()}")
    return grid_from_bounds((x.min(), y.min(), x.max(), y.max()), res, crs)
