"""DEM access: a raster of heights with its CRS, nodata and vertical reference.

Heights are sampled bilinearly at longitude/latitude (degrees). Points outside the raster or
touching a void are reported (NaN plus a status code) and never filled with an invented value.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.enums import MaskFlags
from pyproj import CRS

from stereodem.sensor.geo import geodesy
from stereodem.sensor.errors import CRSError, DEMCoverageError, DEMError, VerticalReferenceError

#: status codes returned by :meth:`DEM.sample`
OK, OUTSIDE, VOID = 0, 1, 2

GEOID, ELLIPSOID = "geoid", "ellipsoid"
_VERTICAL_TAG = "STEREODEM_VERTICAL"


def _vertical_from_crs(crs: CRS | None) -> str | None:
    """Vertical reference said by a CRS: a compound CRS whose vertical part is a geoid height
    (EGM96/EGM2008, any gravity-related height) -> ``"geoid"``; a 3-D CRS with an ellipsoidal
    height axis (EPSG:4979, a projected CRS promoted to 3-D, or a compound CRS with an
    ellipsoidal vertical part) -> ``"ellipsoid"``; otherwise ``None``."""
    if crs is None:
        return None
    try:
        pcrs = CRS.from_user_input(crs)
    except Exception:
        return None
    axes = [a.name.lower() for a in pcrs.axis_info]
    if any("ellipsoidal height" in a for a in axes):
        return ELLIPSOID
    if pcrs.is_compound:
        names = " ".join(str(sub.name) for sub in pcrs.sub_crs_list).lower()
        if "ellipsoid" in names:
            return ELLIPSOID
        if "egm96" in names or "egm2008" in names or "geoid" in names or \
                any("gravity-related" in a for a in axes):
            return GEOID
    return None


def horizontal_crs(crs: CRS) -> CRS:
    """The horizontal part of ``crs`` (the first member of a compound CRS, a 3-D CRS
    demoted to 2-D); a 2-D CRS is returned as it is."""
    crs = CRS.from_user_input(crs)
    if crs.is_compound:
        return crs.sub_crs_list[0]
    if len(crs.axis_info) == 3:
        return crs.to_2d()
    return crs


@dataclass
class DEM:
    """A DEM raster in memory.

    Attributes
    ----------
    heights : ndarray (rows, cols) float32
        Heights in metres, NaN on voids.
    transform : affine.Affine
        GDAL pixel-corner transform to ``crs``.
    crs : pyproj.CRS
        Horizontal CRS of the grid (the vertical part of a file's compound or 3-D CRS goes
        to ``vertical``).
    vertical : {"geoid", "ellipsoid"} or None
        Vertical reference of ``heights``; ``None`` means unknown, and any operation that
        needs ellipsoidal heights raises :class:`VerticalReferenceError`.
    path : str, optional
        Source file, used in error messages.
    """

    heights: np.ndarray
    transform: Affine
    crs: CRS
    vertical: str | None = None
    path: str | None = None
    _lonlat_is_native: bool = field(init=False, repr=False, default=False)

    def __post_init__(self):
        if self.crs is None:
            raise CRSError(f"{self.path or 'DEM'}: the DEM has no CRS")
        self.crs = CRS.from_user_input(self.crs)
        h = np.asarray(self.heights, dtype=np.float32)
        if h.ndim != 2:
            raise DEMError(f"{self.path or 'DEM'}: expected a 2-D height array, got shape {h.shape}")
        self.heights = h
        if self.vertical not in (None, GEOID, ELLIPSOID):
            raise DEMError(f"vertical reference must be 'geoid' or 'ellipsoid', got {self.vertical!r}")
        if not np.isfinite(h).any():
            raise DEMError(f"{self.path or 'DEM'}: the DEM has no valid height (all nodata)")
        geo = self.crs.is_geographic
        self._lonlat_is_native = bool(geo and self.crs.ellipsoid is not None
                                      and abs(self.crs.ellipsoid.semi_major_metre - geodesy.A) < 1e-3
                                      and abs(self.crs.ellipsoid.inverse_flattening - 1 / geodesy.F) < 1e-6)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_file(cls, path, vertical: str | None = None, band: int = 1) -> "DEM":
        """Read a DEM with rasterio.

        ``vertical`` overrides the vertical reference; otherwise it is taken from the file's
        CRS (compound *horizontal + EGM96 height*, or 3-D with ellipsoidal heights, as
        :meth:`write` stores it) or, for files written by older versions, stereodem's own
        ``STEREODEM_VERTICAL`` tag, and is ``None`` (unknown) if neither says. ``crs`` is the
        horizontal part.
        """
        from stereodem.sensor.io.raster import reading_env
        path = str(path)
        try:
            with reading_env(), rasterio.open(path) as ds:
                if ds.crs is None:
                    raise CRSError(f"{path}: the DEM has no CRS")
                flags = ds.mask_flag_enums[band - 1]
                if all(f in (MaskFlags.nodata, MaskFlags.all_valid) for f in flags):
                    # nodata value or none: read straight into float32 (no mask array, no copy)
                    heights = ds.read(band, out_dtype=np.float32)
                    if ds.nodata is not None and np.isfinite(ds.nodata):
                        heights[heights == np.float32(ds.nodata)] = np.nan
                else:                                   # a mask band or alpha: GDAL's mask
                    heights = ds.read(band, masked=True).astype(np.float32).filled(np.nan)
                transform, crs = ds.transform, CRS.from_user_input(ds.crs.to_wkt())
                tag = ds.tags().get(_VERTICAL_TAG)
        except rasterio.errors.RasterioIOError as exc:
            raise DEMError(f"{path}: cannot read the DEM ({exc})") from None
        np.copyto(heights, np.float32(np.nan), where=~np.isfinite(heights))
        vert = vertical or _vertical_from_crs(crs) or (tag.lower() if tag else None)
        return cls(heights, transform, horizontal_crs(crs), vert, path)

    @classmethod
    def bundled(cls) -> "DEM":
        """The bundled real SRTM 3" DEM (eastern Turkey, EGM96 geoid heights)."""
        from importlib import resources
        return cls.from_file(resources.files("stereodem.sensor") / "data" / "srtm_ref.tif", vertical=GEOID)

    # ---------------------------------------------------------------- geometry
    @property
    def grid(self):
        """The DEM's :class:`~stereodem.sensor.geo.grid.MapGrid`."""
        from stereodem.sensor.geo.grid import MapGrid
        return MapGrid(self.transform, self.heights.shape[1], self.heights.shape[0], self.crs)

    @property
    def shape(self):
        return self.heights.shape

    def bounds_lonlat(self):
        """(west, south, east, north) in degrees of the DEM's valid extent (corners densified)."""
        rows, cols = self.shape
        t = np.linspace(0, 1, 21)
        xs = np.concatenate([t * cols, np.full_like(t, cols), t[::-1] * cols, np.zeros_like(t)])
        ys = np.concatenate([np.zeros_like(t), t * rows, np.full_like(t, rows), t[::-1] * rows])
        x, y = self.transform @ (xs, ys)
        lon, lat = geodesy.crs_to_lonlat(x, y, self.crs)
        return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))

    def _lonlat_to_pixel(self, lon, lat):
        lon = np.asarray(lon, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        if self._lonlat_is_native:
            x, y = lon, lat
        else:
            x, y = geodesy.lonlat_to_crs(lon, lat, self.crs)
        col, row = ~self.transform @ (x, y)
        return np.asarray(col) - 0.5, np.asarray(row) - 0.5     # pixel-centre convention

    # ---------------------------------------------------------------- sampling
    def sample(self, lon, lat, *, reference: str | None = ELLIPSOID, return_status=False,
               strict=False):
        """Bilinear heights at ``lon, lat`` (degrees).

        Parameters
        ----------
        reference : {"ellipsoid", "geoid", None}
            Vertical reference of the returned heights; ``None`` returns the raster's own values.
        return_status : bool
            Also return an int8 array: 0 ok, 1 outside the DEM, 2 on or next to a void.
        strict : bool
            Raise :class:`DEMCoverageError` if any point is outside or on a void.

        Returns
        -------
        heights : ndarray float64, metres, NaN where unavailable.
        """
        lon, lat = np.broadcast_arrays(np.asarray(lon, dtype=np.float64),
                                       np.asarray(lat, dtype=np.float64))
        out_shape = lon.shape
        lon, lat = lon.ravel(), lat.ravel()
        c, r = self._lonlat_to_pixel(lon, lat)
        rows, cols = self.shape
        finite = np.isfinite(c) & np.isfinite(r)
        inside = finite & (c >= -1e-9) & (r >= -1e-9) & (c <= cols - 1 + 1e-9) & (r <= rows - 1 + 1e-9)
        c0 = np.clip(np.floor(np.where(inside, c, 0)), 0, max(cols - 2, 0)).astype(np.intp)
        r0 = np.clip(np.floor(np.where(inside, r, 0)), 0, max(rows - 2, 0)).astype(np.intp)
        fc = np.where(inside, c, 0) - c0
        fr = np.where(inside, r, 0) - r0
        c1 = np.minimum(c0 + 1, cols - 1)
        r1 = np.minimum(r0 + 1, rows - 1)
        H = self.heights
        z = ((1 - fr) * ((1 - fc) * H[r0, c0] + fc * H[r0, c1])
             + fr * ((1 - fc) * H[r1, c0] + fc * H[r1, c1])).astype(np.float64)
        z[~inside] = np.nan
        status = np.zeros(lon.shape, dtype=np.int8)
        status[~inside] = OUTSIDE
        status[inside & ~np.isfinite(z)] = VOID
        if strict and status.any():
            n_out, n_void = int((status == OUTSIDE).sum()), int((status == VOID).sum())
            raise DEMCoverageError(
                f"{self.path or 'DEM'}: {n_out} point(s) outside the DEM and {n_void} on voids "
                f"(of {status.size}); DEM extent lon/lat {self.bounds_lonlat()}")
        if reference is not None:
            z = self.convert_heights(lon, lat, z, to=reference)
        z, status = z.reshape(out_shape), status.reshape(out_shape)
        return (z, status) if return_status else z

    def convert_heights(self, lon, lat, z, to: str):
        """Convert heights ``z`` of this DEM's vertical reference to ``to``."""
        if to not in (GEOID, ELLIPSOID):
            raise DEMError(f"unknown vertical reference {to!r}")
        if self.vertical == to:
            return z
        if self.vertical is None:
            raise VerticalReferenceError(
                f"{self.path or 'DEM'}: vertical reference unknown (geoid or ellipsoid?); "
                "say which (vertical='geoid' / --dem-vertical geoid)")
        if to == ELLIPSOID:
            return geodesy.geoid_to_ellipsoid(lon, lat, z)
        return geodesy.ellipsoid_to_geoid(lon, lat, z)

    def to_reference(self, to: str) -> "DEM":
        """A copy of this DEM with heights converted to ``to`` (``geoid`` or ``ellipsoid``)."""
        if self.vertical == to:
            return self
        rows, cols = self.shape
        cc, rr = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
        x, y = self.transform @ (cc, rr)
        lon, lat = geodesy.crs_to_lonlat(x, y, self.crs)
        z = self.convert_heights(lon, lat, self.heights.astype(np.float64), to)
        return DEM(z.astype(np.float32), self.transform, self.crs, to, self.path)

    def height_range(self, reference: str | None = ELLIPSOID):
        """(min, max) of the valid heights, in the requested reference (metres)."""
        d = self if reference is None else self.to_reference(reference)
        return float(np.nanmin(d.heights)), float(np.nanmax(d.heights))

    def write(self, path, *, overwrite=False, creation_options=None):
        """Write as a float32 Cloud-Optimised GeoTIFF with NaN nodata, the vertical reference
        in the CRS (and the old tag), band description and unit (metre).

        ``creation_options``: GDAL COG creation options (see
        :func:`stereodem.sensor.io.raster.write_geotiff`).
        """
        from stereodem.sensor.io.raster import write_geotiff
        what = {GEOID: "height above the EGM96 geoid", ELLIPSOID: "height above the WGS84 ellipsoid"}
        return write_geotiff(path, self.heights.astype(np.float32), self.transform,
                             self.crs, np.nan, overwrite=overwrite, vertical=self.vertical,
                             descriptions=what.get(self.vertical, "height"), units="metre",
                             creation_options=creation_options)


def as_dem(dem, vertical: str | None = None) -> DEM:
    """Accept a :class:`DEM` or a path and return a :class:`DEM`."""
    if isinstance(dem, DEM):
        return dem
    if isinstance(dem, (str, Path)):
        return DEM.from_file(dem, vertical=vertical)
    raise DEMError(f"expected a DEM or a path, got {type(dem).__name__}")
