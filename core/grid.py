"""Map grids: a north-up raster lattice (transform, size, CRS), the one grid type of the
project (DEMs, orthoimages, the stereo output lattice, simulated rasters, uncertainty maps).

The transform is GDAL's pixel-corner affine (rasterio convention): cell ``[i, j]`` has its
centre at ``transform * (j + 0.5, i + 0.5)``. ``width``/``height`` count columns and rows, as
in rasterio's datasets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from affine import Affine
from pyproj import CRS

from stereodem.core import geodesy
from stereodem.core.errors import CRSError, InputError

__all__ = [
    "MapGrid",
    "OnGrid",
    "grid_from_bounds",
    "as_crs",
    "map_crs",
    "crs_unit",
    "posting_text",
]


def as_crs(crs) -> CRS:
    """A :class:`pyproj.CRS` from anything pyproj accepts; :class:`CRSError` otherwise."""
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc}") from None


def map_crs(crs, what: str = "CRS") -> CRS:
    """``crs`` as a :class:`pyproj.CRS` that can carry a map grid (projected or geographic,
    optionally with a vertical part); :class:`CRSError` naming ``what`` for an unknown code
    (``EPSG:999999``), garbage, or a geocentric/engineering CRS."""
    try:
        c = CRS.from_user_input(crs)
    except Exception as exc:
        raise CRSError(
            f"{what}: unknown or unusable CRS {crs!r} ({' '.join(str(exc).split())})"
        ) from None
    horizontal = c.sub_crs_list[0] if c.is_compound and c.sub_crs_list else c
    if not (horizontal.is_projected or horizontal.is_geographic) or horizontal.is_geocentric:
        raise CRSError(f"{what}: CRS {crs!r} ({c.name}) is not a map CRS (projected or geographic)")
    return c


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
        object.__setattr__(self, "crs", as_crs(self.crs))
        t = self.transform
        if abs(t.b) > 0 or abs(t.d) > 0 or t.a <= 0 or t.e >= 0:
            raise InputError(
                f"the grid is not north-up (transform {tuple(t)[:6]}); warp it first (gdalwarp)"
            )
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
        """Map coordinates of cell centres at (fractional) grid ``cols, rows`` (0 = first
        centre)."""
        t = self.transform
        return (
            t.c + t.a * (np.asarray(cols, float) + 0.5),
            t.f + t.e * (np.asarray(rows, float) + 0.5),
        )

    def colrow(self, x, y):
        """Fractional grid (col, row) of map points, cell centres at integers."""
        t = self.transform
        return ((np.asarray(x, float) - t.c) / t.a - 0.5, (np.asarray(y, float) - t.f) / t.e - 0.5)

    def lonlat(self, cols, rows):
        """Longitude/latitude (deg) of cell centres."""
        return geodesy.crs_to_lonlat(*self.xy(cols, rows), self.crs)

    def window(self, row0: int, row1: int) -> MapGrid:
        """The sub-grid of rows ``row0:row1``."""
        return MapGrid(
            self.transform @ Affine.translation(0, row0), self.width, row1 - row0, self.crs
        )

    @property
    def posting(self) -> float:
        """Cell size along x, map units (square cells)."""
        return float(self.transform.a)

    @property
    def unit(self) -> str:
        """The map unit (:func:`crs_unit`); :attr:`res` and :attr:`posting` are in it, metres
        only when it is ``"metre"``."""
        return crs_unit(self.crs)

    @property
    def posting_text(self) -> str:
        """The posting with its unit (:func:`posting_text`): ``"30 m"``, ``"0.000833°"``."""
        return posting_text(self.posting, self.unit)

    def res_report(self) -> dict:
        """The posting for a report: ``res`` (map units), ``res_unit`` (:attr:`unit`), and
        ``res_m`` (the key reports had) only when the unit is the metre: it is not metres
        on a lon/lat or a feet grid."""
        rep = {"res": self.posting, "res_unit": self.unit}
        if rep["res_unit"] == "metre":
            rep["res_m"] = self.posting
        return rep

    def cell_centres(self):
        """Map coordinates ``(x, y)`` of all cell centres, arrays of :attr:`shape`."""
        jj, ii = np.meshgrid(np.arange(self.width), np.arange(self.height))
        return self.xy(jj, ii)


def crs_unit(crs) -> str:
    """The map unit of ``crs`` (its first horizontal axis): ``"metre"``, ``"degree"``, or
    another name as pyproj gives it (``"US survey foot"``); ``""`` when the CRS does not say."""
    crs = as_crs(crs)
    axes = crs.axis_info or (crs.sub_crs_list[0].axis_info if crs.sub_crs_list else [])
    unit = axes[0].unit_name.strip() if axes else ""
    return "metre" if unit.lower() in ("metre", "meter") else unit


def posting_text(value: float, unit: str) -> str:
    """A cell size with its map unit for people: ``"30 m"``, ``"0.000833°"``, ``"100 US
    survey foot"`` (a bare number did not say whether it was metres or degrees)."""
    text = f"{value:g}"
    if unit == "metre":
        return f"{text} m"
    if unit.lower() == "degree":
        return f"{text}°"
    return f"{text} {unit}" if unit else text


def grid_from_bounds(bounds, res, crs) -> MapGrid:
    """A grid covering ``bounds`` (west, south, east, north) with posting ``res``, snapped outward
    to multiples of ``res`` (so that grids of the same posting align)."""
    res = float(res)
    if not np.isfinite(res) or res <= 0:
        raise InputError(f"grid posting must be positive, got {res}")
    w, s, e, n = (float(v) for v in bounds)
    if not all(np.isfinite([w, s, e, n])) or e <= w or n <= s:
        raise InputError(f"empty or invalid grid bounds {bounds}")
    if not all(math.isfinite(v / res) for v in (w, s, e, n)):
        raise InputError(f"grid posting {res:g} is too fine for the bounds {bounds}")
    # the snapped edges in whole postings (Python integers: exact, no overflow)
    i0, i1 = math.floor(w / res), math.ceil(e / res)
    j0, j1 = math.floor(s / res), math.ceil(n / res)
    x0, y1 = i0 * res, j1 * res
    width, height = i1 - i0, j1 - j0
    # every corner, as the grid's bounds compute them (origin + cells x posting)
    try:
        corners = (x0, y1, x0 + width * res, y1 - height * res)
    except OverflowError:  # a cell count beyond any float
        corners = (math.inf,)
    if not all(math.isfinite(v) for v in corners):
        raise InputError(
            f"grid posting {res:g} does not fit the bounds {bounds} (its snapped corners "
            "overflow); give a posting of the order of the area's size or less"
        )
    return MapGrid(Affine(res, 0.0, x0, 0.0, -res, y1), max(width, 1), max(height, 1), crs)


class OnGrid:
    """Mixin for data held on a :class:`MapGrid` (attribute ``grid``): its transform, CRS,
    shape and posting as shortcuts."""

    grid: MapGrid

    @property
    def transform(self) -> Affine:
        return self.grid.transform

    @property
    def crs(self) -> CRS:
        return self.grid.crs

    @property
    def shape(self) -> tuple:
        return self.grid.shape

    @property
    def posting(self) -> float:
        return self.grid.posting
