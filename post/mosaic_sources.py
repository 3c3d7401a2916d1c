"""The DEMs of a mosaic: opened header-only, reconciled to one CRS and vertical reference,
placed on one output grid, and sorted into used / skipped.

Nothing here reads heights: a :class:`Source` is a file's georeferencing (GDAL pixel-corner
transform, horizontal CRS), its vertical reference, its σ layer if it has one, and its
footprint in the output CRS, so hundreds of DEMs cost a few kB. The heights are read block by
block by :mod:`stereodem.post.mosaic`.

σ layer of a DEM (1σ vertical, metres): a band of the file whose description starts with
``sigma`` (as :mod:`stereodem.post.mosaic` writes), or the ``<stem>_sigma_vertical.tif``
beside it on the same grid (as ``stereodem uncertainty`` writes).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS
from rasterio.warp import calculate_default_transform, transform_bounds

from stereodem.core.dem import (
    ELLIPSOID,
    GEOID,
    check_georeferenced,
    check_heights_band,
    file_vertical,
    horizontal_crs,
    other_geoid,
)
from stereodem.core.errors import (
    CRSError,
    DEMError,
    InputError,
    VerticalReferenceError,
    not_found,
)
from stereodem.core.grid import MapGrid, as_crs
from stereodem.core.raster import VERTICAL_TAG, unreadable

log = logging.getLogger(__name__)

__all__ = [
    "Source",
    "mosaic_geoid",
    "open_source",
    "open_sources",
    "output_grid",
    "reconcile_vertical",
    "select_sources",
]


@dataclass(frozen=True)
class Source:
    """One input DEM of a mosaic (georeferencing only; picklable for Dask workers).

    Attributes
    ----------
    path : str
    order : int
        Position on the command line (``first`` / ``last`` follow it).
    crs_wkt : str
        Horizontal CRS of the file (WKT).
    transform : affine.Affine
        GDAL pixel-corner transform of the file.
    width, height : int
    vertical : {"geoid", "ellipsoid"} or None
        Vertical reference of the heights (None: the file does not say).
    geoid_wkt : str or None
        With ``vertical == "geoid"``: the vertical CRS (WKT) when the file names a geoid other
        than EGM96 (:func:`stereodem.core.dem.other_geoid`).
    sigma : (path, band) or None
        Where the DEM's 1σ vertical layer (m) is.
    bounds : tuple
        (west, south, east, north) of the footprint in the output CRS (set by
        :func:`output_grid`; the file's own CRS before).
    shift_m : (float, float)
        Co-registration: metres along x/y (grid east/north) by which the DEM's grid is
        moved before mosaicking (its grid's metres: the CRS's units on a projected grid,
        :func:`~stereodem.post.warp.translated`).
    dz : float
        Co-registration: metres subtracted from its heights.
    """

    path: str
    order: int
    crs_wkt: str
    transform: Affine
    width: int
    height: int
    vertical: str | None
    sigma: tuple | None = None
    bounds: tuple = ()
    shift_m: tuple = (0.0, 0.0)
    dz: float = 0.0
    geoid_wkt: str | None = None
    info: dict = field(default_factory=dict, compare=False)

    @property
    def crs(self) -> CRS:
        return CRS.from_wkt(self.crs_wkt)

    @property
    def native_bounds(self):
        t = self.transform
        return (t.c, t.f + t.e * self.height, t.c + t.a * self.width, t.f)


def _sigma_layer(path: Path, ds) -> tuple | None:
    for i, desc in enumerate(ds.descriptions, start=1):
        if desc and desc.strip().lower().startswith("sigma"):
            return (str(path), i)
    side = path.with_name(f"{path.stem}_sigma_vertical.tif")
    if side.exists():
        try:
            with rasterio.open(side) as s:
                if (s.width, s.height) == (ds.width, ds.height) and s.transform.almost_equals(
                    ds.transform
                ):
                    return (str(side), 1)
        except rasterio.errors.RasterioIOError:
            pass
        log.warning("%s: not on the grid of %s; its σ is not used", side, path)
    return None


def open_source(path, order: int = 0, *, vertical: str | None = None) -> Source:
    """A DEM file's header as a :class:`Source`; ``vertical`` applies when the file does not
    say its vertical reference. One-line :class:`DEMError` / :class:`CRSError` naming the file
    when it cannot be used."""
    path = Path(path)
    if not path.exists():
        raise DEMError(not_found(path, "DEM"))
    try:
        with rasterio.open(path) as ds:
            check_georeferenced(path, ds)  # a CRS and a geotransform
            check_heights_band(path, ds)  # not an image's band, not an orthoimage
            t = ds.transform
            if abs(t.b) > 0 or abs(t.d) > 0 or t.a <= 0 or t.e >= 0:
                raise DEMError(
                    f"{path}: the DEM's grid is not north-up (transform {tuple(t)[:6]}); "
                    "warp it first (gdalwarp)"
                )
            crs = CRS.from_wkt(ds.crs.to_wkt())
            tag = ds.tags().get(VERTICAL_TAG)
            vert = file_vertical(path, crs, tag, vertical)
            geoid = other_geoid(crs) if vert == GEOID else None
            return Source(
                str(path),
                order,
                horizontal_crs(crs).to_wkt(),
                t,
                ds.width,
                ds.height,
                vert,
                _sigma_layer(path, ds),
                bounds=tuple(ds.bounds),
                geoid_wkt=geoid.to_wkt() if geoid is not None else None,
            )
    except rasterio.errors.RasterioIOError as exc:
        raise DEMError(unreadable(path, "DEM", exc)) from None


def open_sources(paths, *, vertical: str | None = None) -> list[Source]:
    """Headers of all DEMs, in order; the first unusable file stops the job (one line)."""
    if not paths:
        raise InputError("no DEM given")
    seen = {}
    for p in paths:
        if not isinstance(p, str | os.PathLike):  # a DEM object, an array: read block by block
            raise InputError(
                f"a mosaic reads its DEMs from files, block by block: got a "
                f"{type(p).__name__} among the paths (write it first: DEM.write)"
            )
        key = str(Path(p).resolve())
        if key in seen:
            raise InputError(f"{p}: given twice (also as {seen[key]})")
        seen[key] = p
    return [open_source(p, i, vertical=vertical) for i, p in enumerate(paths)]


def reconcile_vertical(sources, target: str | None = None) -> str | None:
    """The mosaic's vertical reference: ``target`` or the first DEM's.

    DEMs whose reference differs are converted block by block with EGM96 (``geoid`` <->
    ``ellipsoid``); a DEM whose reference is unknown, among DEMs that say theirs, is refused
    (:class:`VerticalReferenceError`, one line naming it): mixing them would put the geoid
    undulation (tens of metres) into the seams. All unknown: heights are mosaicked as they are
    and the output says nothing about its vertical reference.
    """
    if target not in (None, GEOID, ELLIPSOID):
        raise InputError(f"vertical reference must be 'geoid' or 'ellipsoid', got {target!r}")
    known = [s for s in sources if s.vertical is not None]
    unknown = [s for s in sources if s.vertical is None]
    if not known:
        if target is not None:
            raise VerticalReferenceError(
                f"{sources[0].path}: vertical reference unknown; cannot convert to {target} "
                "(say it with --dem-vertical)"
            )
        return None
    if unknown:
        names = ", ".join(s.path for s in unknown[:3]) + (" ..." if len(unknown) > 3 else "")
        raise VerticalReferenceError(
            f"{names}: vertical reference unknown while {known[0].path} says {known[0].vertical}; "
            "say it with --dem-vertical geoid|ellipsoid"
        )
    return target or sources[0].vertical


def mosaic_geoid(sources, target: str | None) -> str | None:
    """The vertical CRS (WKT) of a geoid mosaic's heights when its geoid is not EGM96: the
    first geoid DEM's; None for EGM96 or a mosaic of other heights. DEMs above different
    geoids (EGM2008 and EGM96 tiles), or a conversion with EGM96 (the only geoid of the
    conversions here) of heights above another, are mosaicked with a warning naming them:
    their seams carry the separation of the geoids (EGM2008 - EGM96: within about 1 m over
    most land, a few metres in high mountains)."""

    def name(s):
        return CRS.from_wkt(s.geoid_wkt).name if s.geoid_wkt else "EGM96 height"

    geoids = [s for s in sources if s.vertical == GEOID]
    names = {name(s) for s in geoids}
    converted = [s for s in sources if s.vertical is not None and s.vertical != target]
    mixed = len(names) > 1 or (converted and names - {"EGM96 height"})
    if mixed:
        log.warning(
            "%s: heights above %s mosaicked as %s heights (conversions with EGM96): the seams "
            "carry the separation of the geoids (EGM2008 - EGM96: within about 1 m over most "
            "land, a few metres in high mountains)",
            ", ".join(s.path for s in geoids[:3]) + (" ..." if len(geoids) > 3 else ""),
            " and ".join(sorted(names)),
            target,
        )
    if target != GEOID or not geoids:
        return None
    return geoids[0].geoid_wkt


#: GDAL's largest raster side (its C int)
MAX_RASTER_SIDE = 2**31 - 1


def _anchor(first: Source, crs: CRS, res: tuple[float, float]):
    """Origin of the output lattice: the first DEM's when it is in the output CRS at ``res``
    (so its cells are copied, not resampled), else multiples of ``res``."""
    t = first.transform
    rx, ry = res
    if first.crs.equals(crs) and np.isclose(t.a, rx, rtol=1e-9) and np.isclose(-t.e, ry, rtol=1e-9):
        return t.c % rx, t.f % ry
    return 0.0, 0.0


def output_grid(sources, *, crs=None, res: float | None = None, bounds=None):
    """The mosaic's grid and the sources with their footprints in its CRS.

    ``crs`` defaults to the first DEM's, ``res`` to its posting (reprojected to ``crs`` when
    that differs), ``bounds`` (west, south, east, north in ``crs``) to the union of the
    footprints. The lattice is aligned with the first DEM's when possible. The first DEM's
    posting is its x and y posting, which a lon/lat DEM at high latitude has unequal (the
    Copernicus DEM above 60 N: 2" of longitude by 1" of latitude); ``res`` given is square.
    """
    first = sources[0]
    crs = as_crs(crs) if crs is not None else first.crs
    if crs.is_compound or len(crs.axis_info) == 3:
        crs = horizontal_crs(crs)
    placed = []
    for s in sources:
        try:
            b = transform_bounds(s.crs_wkt, crs.to_wkt(), *s.native_bounds, densify_pts=21)
        except Exception as exc:
            raise CRSError(
                f"{s.path}: cannot transform its footprint to {crs.name} ({exc})"
            ) from None
        if not np.all(np.isfinite(b)):
            raise CRSError(f"{s.path}: its footprint has no place in {crs.name}")
        placed.append(replace(s, bounds=tuple(float(v) for v in b)))
    if crs.is_geographic:
        placed = _beside_each_other(placed, bounds)
    if res is None:
        if first.crs.equals(crs):
            rx, ry = float(first.transform.a), float(-first.transform.e)
        else:
            t, _, _ = calculate_default_transform(
                first.crs_wkt, crs.to_wkt(), first.width, first.height, *first.native_bounds
            )
            rx = ry = float(f"{t.a:.3g}")
    else:
        rx = ry = float(res)
    if not (np.isfinite(rx) and np.isfinite(ry) and rx > 0 and ry > 0):
        raise InputError(f"--res must be positive, got {res:g}")
    if bounds is None:
        b = np.array([p.bounds for p in placed])
        bounds = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
    w, s_, e, n = (float(v) for v in bounds)
    if not (e > w and n > s_):
        raise InputError(f"empty mosaic bounds {bounds}")
    ox, oy = _anchor(first, crs, (rx, ry))
    with np.errstate(over="ignore", invalid="ignore"):  # a posting of 1e-300: refused below
        x0 = ox + np.floor((w - ox) / rx + 1e-9) * rx
        x1 = ox + np.ceil((e - ox) / rx - 1e-9) * rx
        y0 = oy + np.floor((s_ - oy) / ry + 1e-9) * ry
        y1 = oy + np.ceil((n - oy) / ry - 1e-9) * ry
        cols, rows = (x1 - x0) / rx, (y1 - y0) / ry
    if not (cols <= MAX_RASTER_SIDE and rows <= MAX_RASTER_SIDE):
        # 1e-30 streamed its blocks for ever, 5e-324 (NaN bounds) was a ValueError
        raise InputError(
            f"a mosaic grid of {cols:.3g} x {rows:.3g} cells at posting {rx:g} is beyond "
            f"GDAL's largest raster ({MAX_RASTER_SIDE} cells a side): choose a coarser --res"
        )
    width, height = int(round(cols)), int(round(rows))
    grid = MapGrid(Affine(rx, 0.0, x0, 0.0, -ry, y1), max(width, 1), max(height, 1), crs)
    return grid, placed


def _beside_each_other(placed, bounds=None):
    """Footprints in a geographic output CRS, degrees, moved by whole turns to the longitudes
    of the first (or of ``bounds``, the mosaic's extent when given), so that DEMs on both sides
    of the antimeridian lie side by side: a footprint that crosses it (west > east, as GDAL
    gives it) ends east of 180, a DEM west of -180 + 180 is moved 360 degrees east, and a
    geographic DEM's grid moves with it (a projected DEM is warped to any longitude). Without
    this, the tiles at 179.9 and -180 E made a mosaic 360 degrees wide and a DEM crossing 180
    was skipped as outside."""
    w0, _, e0, _ = bounds if bounds is not None else placed[0].bounds
    centre = (w0 + e0 + (360.0 if w0 > e0 else 0.0)) / 2.0
    out = []
    for s in placed:
        w, south, e, north = s.bounds
        e += 360.0 if w > e else 0.0
        turn = 360.0 * round((centre - (w + e) / 2.0) / 360.0)
        t = s.transform
        if turn and s.crs.is_geographic:
            t = Affine.translation(turn, 0.0) @ t
        out.append(replace(s, transform=t, bounds=(w + turn, south, e + turn, north)))
    return out


def _overlaps(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def select_sources(sources, grid: MapGrid):
    """(used, skipped, islands): DEMs whose footprint misses the mosaic's extent are skipped
    (``{"path", "reason"}``); ``islands`` names used DEMs that overlap no other (kept: a
    mosaic may join disjoint DEMs, but a DEM far from the rest usually is a mistake)."""
    used, skipped = [], []
    for s in sources:
        if _overlaps(s.bounds, grid.bounds):
            used.append(s)
        else:
            skipped.append(dict(path=s.path, reason="does not overlap the mosaic's extent"))
            log.warning("%s: does not overlap the mosaic's extent; skipped", s.path)
    islands = []
    if len(used) > 1:
        b = np.array([s.bounds for s in used])
        ov = (
            (b[:, None, 0] < b[None, :, 2])
            & (b[None, :, 0] < b[:, None, 2])
            & (b[:, None, 1] < b[None, :, 3])
            & (b[None, :, 1] < b[:, None, 3])
        )
        np.fill_diagonal(ov, False)
        islands = [used[i].path for i in np.flatnonzero(~ov.any(axis=1))]
        for p in islands:
            log.warning("%s: overlaps no other DEM of the mosaic", p)
    if not used:
        raise InputError("no DEM overlaps the mosaic's extent")
    return used, skipped, islands
