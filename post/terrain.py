"""Terrain attributes on DEM grids: metric pixel size, gradient, slope, aspect, hillshade.

Works on projected grids (metres) and on geographic grids (degrees): for the latter the pixel
size in metres is computed per row from the WGS84 meridian and prime-vertical radii of
curvature at the row's latitude, so slopes are right on an SRTM-style lon/lat DEM.

Arrays follow the DEM convention: ``heights[row, col]`` float32 with NaN voids, an affine
pixel-corner ``transform`` (GDAL) and a CRS. Rows run north to south when the transform's
``e`` term is negative (the usual case); the east/north gradients account for the signs.
"""

from __future__ import annotations

import numpy as np
from pyproj import CRS

from stereodem.core import geodesy
from stereodem.core.errors import CRSError
from stereodem.core.geodesy import metres_per_degree


def _is_geographic(crs) -> bool:
    try:
        return bool(CRS.from_user_input(crs).is_geographic)
    except Exception as exc:
        raise CRSError(f"unusable CRS {crs!r}: {exc}") from None


def _linear_unit_factor(crs) -> float:
    c = CRS.from_user_input(crs)
    try:
        f = c.axis_info[0].unit_conversion_factor
    except (IndexError, AttributeError):
        f = 1.0
    return float(f or 1.0)


def check_not_rotated(transform, path=None) -> None:
    """The terrain derivatives need a grid without rotation terms: :class:`CRSError`, naming
    the DEM file ``path`` when given, otherwise."""
    if abs(transform.b) > 1e-12 * abs(transform.a) or abs(transform.d) > 1e-12 * abs(transform.e):
        raise CRSError(
            f"{path or 'DEM'}: rotated DEM grids are not supported; warp the DEM to a north-up "
            "grid first (gdalwarp)"
        )


def pixel_size_m(transform, crs, shape):
    """Pixel size in metres along columns (east) and rows (north), per row.

    Parameters
    ----------
    transform : affine.Affine
        Pixel-corner transform; rotation terms must be zero (north-up grid).
    crs : CRS-like
        Geographic (degrees) or projected CRS.
    shape : (rows, cols)

    Returns
    -------
    dx, dy : ndarray float64 of shape (rows, 1)
        Signed metres per pixel step: ``dx`` eastwards per column step, ``dy`` northwards per
        row step (negative for a north-up grid).
    """
    check_not_rotated(transform)
    rows = shape[0]
    if _is_geographic(crs):
        lat = transform.f + transform.e * (np.arange(rows) + 0.5)
        mlon, mlat = metres_per_degree(lat)
        dx, dy = transform.a * mlon, transform.e * mlat
    else:
        f = _linear_unit_factor(crs)
        dx = np.full(rows, transform.a * f)
        dy = np.full(rows, transform.e * f)
    return np.asarray(dx, float)[:, None], np.asarray(dy, float)[:, None]


def gradient(heights, transform, crs):
    """East and north height gradients (dimensionless, m/m) by central differences.

    Edge cells use one-sided differences; a cell next to a void gets NaN (as in ``gdaldem``).

    Returns
    -------
    dzde, dzdn : ndarray float64
    """
    z = np.asarray(heights)
    dx, dy = pixel_size_m(transform, crs, z.shape)
    if z.shape[0] < 2 or z.shape[1] < 2:
        nan = np.full(z.shape, np.nan)
        return nan, nan.copy()
    return _gradient_rows(z, dx, dy, 0, z.shape[0])


def gradient_at(heights, transform, crs, rows, cols):
    """:func:`gradient` at the cells ``rows, cols`` (integer indices) only, by the same
    arithmetic (``numpy.gradient``'s central differences, one-sided on the grid's edges), so
    the values equal those of the whole grid's gradient there; cost proportional to the cells
    asked for, not to the grid.

    Returns
    -------
    dzde, dzdn : ndarray float64 of the shape of ``rows``
    """
    z = np.asarray(heights, dtype=np.float64)
    rows, cols = np.asarray(rows, np.intp), np.asarray(cols, np.intp)
    nr, nc = z.shape
    if nr < 2 or nc < 2:
        nan = np.full(rows.shape, np.nan)
        return nan, nan.copy()
    dx, dy = pixel_size_m(transform, crs, z.shape)
    return (
        _central_difference(z, rows, cols, axis=1) / dx[rows, 0],
        _central_difference(z, rows, cols, axis=0) / dy[rows, 0],
    )


def _central_difference(z, rows, cols, axis):
    """``numpy.gradient(z)[axis]`` at ``rows, cols``: ``(f[k+1] - f[k-1]) / 2`` inside,
    ``f[1] - f[0]`` and ``f[n-1] - f[n-2]`` on the edges (unit spacing, edge_order 1)."""
    k = rows if axis == 0 else cols
    n = z.shape[axis]
    hi = np.minimum(k + 1, n - 1)
    lo = np.maximum(k - 1, 0)
    if axis == 0:
        diff = z[hi, cols] - z[lo, cols]
    else:
        diff = z[rows, hi] - z[rows, lo]
    inner = (k > 0) & (k < n - 1)
    return np.where(inner, diff / 2.0, diff)


_DEG_PER_RAD = 180.0 / np.pi

#: rows of one band of :func:`slope_deg`'s work: its float64 temporaries stay a few MB
#: (in cache, and reused by the allocator instead of mapped afresh for each grid)
SLOPE_BAND_ROWS = 64


def slope_deg(heights, transform, crs, *, rows: slice | None = None):
    """Slope in degrees (0 flat, 90 vertical), NaN on and next to voids.

    ``rows`` (a slice, step 1): only those rows of the grid, the others read as their
    neighbours; equal to ``slope_deg(heights, transform, crs)[rows]``. The numbers are those
    of :func:`gradient`, worked out in bands of :data:`SLOPE_BAND_ROWS` rows."""
    z = np.asarray(heights)
    r0, r1, _ = (rows if rows is not None else slice(None)).indices(z.shape[0])
    if z.shape[0] < 2 or z.shape[1] < 2:
        return np.full((max(r1 - r0, 0), z.shape[1]), np.nan)
    dx, dy = pixel_size_m(transform, crs, z.shape)
    out = np.empty((max(r1 - r0, 0), z.shape[1]))
    for b0 in range(r0, r1, SLOPE_BAND_ROWS):
        b1 = min(b0 + SLOPE_BAND_ROWS, r1)
        ge, gn = _gradient_rows(z, dx, dy, b0, b1)
        band = out[b0 - r0 : b1 - r0]
        np.hypot(ge, gn, out=band)
        np.arctan(band, out=band)
        np.multiply(band, _DEG_PER_RAD, out=band)  # numpy's degrees: x * (180 / pi)
    return out


def _gradient_rows(z, dx, dy, r0, r1):
    """East and north gradients (m/m) of rows ``r0:r1`` of ``z``, ``numpy.gradient``'s bit
    for bit: its differences (``(f[k+1] − f[k−1]) / 2`` inside, ``f[1] − f[0]`` and
    ``f[n−1] − f[n−2]`` on the edges) divided by the pixel size ``dx``/``dy`` (m, per row),
    taken in one division by ``2·size`` inside (halving is exact, so ``(d / 2) / s`` equals
    ``d / (2 s)``)."""
    n_r, n_c = z.shape
    f64 = np.float64
    band = z[r0:r1]
    sx = dx[r0:r1]
    ge = np.empty(band.shape, f64)
    np.subtract(band[:, 2:], band[:, :-2], out=ge[:, 1:-1], dtype=f64)
    ge[:, 1:-1] /= 2.0 * sx
    np.subtract(band[:, 1:2], band[:, :1], out=ge[:, :1], dtype=f64)
    np.subtract(band[:, -1:], band[:, -2:-1], out=ge[:, -1:], dtype=f64)
    ge[:, :1] /= sx
    ge[:, -1:] /= sx
    gn = np.empty(band.shape, f64)
    i0, i1 = max(r0, 1), min(r1, n_r - 1)  # rows with both neighbours
    if i1 > i0:
        inner = gn[i0 - r0 : i1 - r0]
        np.subtract(z[i0 + 1 : i1 + 1], z[i0 - 1 : i1 - 1], out=inner, dtype=f64)
        inner /= 2.0 * dy[i0:i1]
    if r0 == 0:
        np.subtract(z[1], z[0], out=gn[0], dtype=f64)
        gn[0] /= dy[0]
    if r1 == n_r:
        np.subtract(z[-1], z[-2], out=gn[-1], dtype=f64)
        gn[-1] /= dy[-1]
    return ge, gn


def aspect_deg(heights, transform, crs):
    """Aspect in degrees clockwise from north, the direction the slope faces (downhill)."""
    ge, gn = gradient(heights, transform, crs)
    return np.degrees(np.arctan2(-ge, -gn)) % 360.0


def hillshade(heights, transform, crs, *, azimuth=315.0, altitude=45.0, z_factor=1.0):
    """Hillshade in [0, 1] (NaN on voids) for a light at ``azimuth`` (deg from north) and
    ``altitude`` (deg above the horizon)."""
    ge, gn = gradient(heights, transform, crs)
    ge, gn = ge * z_factor, gn * z_factor
    az, alt = np.radians(azimuth), np.radians(altitude)
    # light direction (east, north, up) and the surface normal (-ge, -gn, 1)/|.|
    le, ln, lu = np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)
    shade = (-ge * le - gn * ln + lu) / np.sqrt(1.0 + ge**2 + gn**2)
    return np.clip(shade, 0.0, 1.0)


def grid_centre_lonlat(transform, crs, shape):
    """Longitude and latitude (deg) of the grid centre."""
    x, y = transform @ (shape[1] / 2.0, shape[0] / 2.0)
    lon, lat = geodesy.crs_to_lonlat(x, y, crs)
    return float(lon), float(lat)
