"""WGS84 geodesy: geodetic <-> ECEF <-> local east/north/up, UTM zones, EGM96 geoid.

Conventions
-----------
* Geodetic coordinates are longitude and latitude in degrees and height in metres above
  the WGS84 ellipsoid (EPSG:4979 with axis order lon, lat, h).
* ECEF (EPSG:4978) coordinates are metres.
* Local frames are east/north/up (ENU) in metres, right-handed.

Coordinate conversions go through pyproj; the ray/height intersection used by every physical
sensor model lives here as well, because it is pure ellipsoid geometry.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from stereodem.core import localfit
from stereodem.core.errors import CRSError, InputError

# WGS84 constants
A = 6378137.0  #: semi-major axis, m
F = 1.0 / 298.257223563  #: flattening
B = A * (1.0 - F)  #: semi-minor axis, m
E2 = F * (2.0 - F)  #: first eccentricity squared
EP2 = E2 / (1.0 - E2)  #: second eccentricity squared
OMEGA_EARTH = 7.2921150e-5  #: Earth rotation rate, rad/s
GM = 3.986004418e14  #: geocentric gravitational constant, m^3/s^2

WGS84_3D = CRS.from_epsg(4979)
ECEF = CRS.from_epsg(4978)


@functools.cache
def transformer(src, dst) -> Transformer:
    """Cached ``Transformer.from_crs(src, dst, always_xy=True)``."""
    return Transformer.from_crs(CRS.from_user_input(src), CRS.from_user_input(dst), always_xy=True)


def _as_float_arrays(*arrays):
    out = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in arrays])
    return [np.array(a) for a in out]


def geodetic_to_ecef(lon, lat, h):
    """Geodetic (deg, deg, m above ellipsoid) to ECEF (m). Returns ``(x, y, z)`` arrays."""
    lon, lat, h = _as_float_arrays(lon, lat, h)
    return transformer(4979, 4978).transform(lon, lat, h)


def _degrees(tolerance_m: float) -> float:
    """A tolerance in metres as degrees of latitude or longitude (a degree of longitude is
    shorter than :data:`A` pi / 180, so the bound holds for both)."""
    return tolerance_m / (np.pi / 180.0 * A)


def ecef_to_geodetic(x, y, z, *, tolerance_m: float | None = None):
    """ECEF (m) to geodetic ``(lon, lat, h)`` in degrees and metres above the ellipsoid.

    PROJ's closed-form inverse is exact to micrometres for terrain heights (-500 to 9000 m)
    and to about 5 mm at orbit heights (700-900 km).

    ``tolerance_m``: many points in a small extent (a stereo tile's) may be converted by a
    polynomial fitted to PROJ's values that is checked to reproduce them within this many
    metres (:func:`stereodem.core.localfit.fitted`; 3 times faster on a tile's 250 000
    points); None: PROJ for every point.
    """
    x, y, z = _as_float_arrays(x, y, z)
    t = transformer(4978, 4979).transform
    if tolerance_m is not None:
        tol = _degrees(tolerance_m)
        out = localfit.fitted(t, (x.ravel(), y.ravel(), z.ravel()), (tol, tol, tolerance_m))
        if out is not None:
            return tuple(a.reshape(x.shape) for a in out)
    return t(x, y, z)


def enu_basis(lon, lat):
    """Unit vectors east, north, up in ECEF at geodetic ``lon, lat`` (degrees).

    Returns an array of shape ``(..., 3, 3)`` whose rows are east, north, up, so that
    ``enu = basis @ d_ecef`` for a vector ``d_ecef``.
    """
    lam = np.radians(np.asarray(lon, dtype=np.float64))
    phi = np.radians(np.asarray(lat, dtype=np.float64))
    lam, phi = np.broadcast_arrays(lam, phi)
    sl, cl, sp, cp = np.sin(lam), np.cos(lam), np.sin(phi), np.cos(phi)
    zero = np.zeros_like(sl)
    east = np.stack([-sl, cl, zero], axis=-1)
    north = np.stack([-sp * cl, -sp * sl, cp], axis=-1)
    up = np.stack([cp * cl, cp * sl, sp], axis=-1)
    return np.stack([east, north, up], axis=-2)


def ecef_to_enu(x, y, z, lon0, lat0, h0):
    """ECEF points to a local ENU frame with origin at geodetic ``(lon0, lat0, h0)``."""
    x0, y0, z0 = geodetic_to_ecef(lon0, lat0, h0)
    d = np.stack(_as_float_arrays(x - x0, y - y0, z - z0), axis=-1)
    e = enu_basis(lon0, lat0) @ d[..., None]
    return e[..., 0, 0], e[..., 1, 0], e[..., 2, 0]


def enu_to_ecef(e, n, u, lon0, lat0, h0):
    """Local ENU (m) with origin at geodetic ``(lon0, lat0, h0)`` to ECEF."""
    x0, y0, z0 = geodetic_to_ecef(lon0, lat0, h0)
    v = np.stack(_as_float_arrays(e, n, u), axis=-1)
    basis = enu_basis(lon0, lat0)
    d = np.swapaxes(basis, -1, -2) @ v[..., None]
    return x0 + d[..., 0, 0], y0 + d[..., 1, 0], z0 + d[..., 2, 0]


def _mean_without_nan(a) -> float:
    """``np.nanmean`` of ``a`` as a float, NaN (no warning) when every value is NaN."""
    a = np.asarray(a, dtype=np.float64).ravel()
    a = a[~np.isnan(a)]
    return float(a.mean()) if a.size else float("nan")


def lon_beside(lon, centre):
    """Longitudes ``lon`` (degrees) moved by whole turns to within 180 degrees of ``centre``:
    -179.99 is 180.01 beside a grid centred at 179.9. The one rule by which a longitude is
    put beside a lon/lat grid (a DEM's pixels, the simulator's footprint on its DEM)."""
    lon = np.asarray(lon, dtype=np.float64)
    return lon + 360.0 * np.round((centre - lon) / 360.0)


def utm_epsg(lon, lat) -> int:
    """EPSG code of the WGS84 UTM zone containing ``(lon, lat)`` (degrees).

    Uses the standard 6-degree zones with the Norway/Svalbard exceptions; for arrays, the
    zone of the mean position is returned (one zone per product), the longitudes averaged
    beside the first one (:func:`lon_beside`): points at 179.9 E and 179.9 W are near 180,
    not at 0 E.
    """
    lon = np.asarray(lon, dtype=np.float64)
    if lon.ndim and np.isfinite(lon).any():
        lon = lon_beside(lon, lon[np.isfinite(lon)].flat[0])
    lon, lat = _mean_without_nan(lon), _mean_without_nan(lat)
    if not (np.isfinite(lon) and np.isfinite(lat)) or abs(lat) > 90:
        raise CRSError(f"cannot choose a UTM zone for lon={lon}, lat={lat}")
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = int((lon + 180.0) // 6.0) + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    if 72.0 <= lat < 84.0:
        for lo, hi, z in ((0, 9, 31), (9, 21, 33), (21, 33, 35), (33, 42, 37)):
            if lo <= lon < hi:
                zone = z
    zone = min(max(zone, 1), 60)
    return (32600 if lat >= 0 else 32700) + zone


def utm_crs(lon, lat) -> CRS:
    """The UTM :class:`pyproj.CRS` for ``(lon, lat)``; see :func:`utm_epsg`."""
    return CRS.from_epsg(utm_epsg(lon, lat))


def metres_in_crs(metres: float, crs) -> float:
    """A length in metres in the horizontal units of ``crs`` (degrees for a geographic CRS:
    the smaller of a degree of latitude or longitude, so that a bound stays a bound)."""
    crs = CRS.from_user_input(crs)
    if crs.is_geographic:
        return _degrees(metres)
    unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
    return metres / unit if unit else metres


def lonlat_to_crs(lon, lat, crs, *, tolerance: float | None = None):
    """Longitude/latitude (deg) to ``(x, y)`` in ``crs``.

    ``tolerance`` (units of ``crs``): as for :func:`ecef_to_geodetic`, many points in a small
    extent may be projected by a polynomial checked against PROJ within it (8 times faster
    for a UTM projection of a stereo tile's points); None: PROJ for every point.
    """
    lon, lat = _as_float_arrays(lon, lat)
    t = transformer(4326, _crs_key(crs)).transform
    if tolerance is not None:
        out = localfit.fitted(t, (lon.ravel(), lat.ravel()), (tolerance, tolerance))
        if out is not None:
            return tuple(a.reshape(lon.shape) for a in out)
    return t(lon, lat)


def crs_to_lonlat(x, y, crs):
    """``(x, y)`` in ``crs`` to longitude/latitude (deg)."""
    x, y = _as_float_arrays(x, y)
    return transformer(_crs_key(crs), 4326).transform(x, y)


def _crs_key(crs):
    if crs is None:
        raise CRSError("no CRS given")
    try:
        return CRS.from_user_input(crs).to_wkt()
    except Exception as exc:  # pyproj raises its own CRSError subclasses
        raise CRSError(f"unusable CRS {crs!r}: {exc}") from None


# --------------------------------------------------------------------------- geoid (EGM96)


def egm96_path() -> Path:
    """Path of the bundled EGM96 15' geoid grid (GTX, geoid height above WGS84, metres)."""
    return Path(resources.files("stereodem.core") / "data" / "egm96_15.gtx")


@functools.cache
def _geoid_transformer(path: str) -> Transformer:
    # PROJ's vgridshift: z_out = z_in + multiplier * N(lon, lat). With multiplier=1 it turns
    # a geoid height into an ellipsoidal height, h = H + N.
    pipeline = f"+proj=vgridshift +grids={path} +multiplier=1"
    return Transformer.from_pipeline(pipeline)


def geoid_undulation(lon, lat, grid: str | Path | None = None):
    """EGM96 geoid undulation N (m, geoid above ellipsoid) at ``lon, lat`` (deg).

    Bilinear interpolation in the bundled 15-arc-minute grid, through PROJ's ``vgridshift``.
    """
    lon, lat = _as_float_arrays(lon, lat)
    path = str(grid or egm96_path())
    t = _geoid_transformer(path)
    # a bare vgridshift pipeline takes degrees (checked: +17.16 m at 0N 0E, -104.7 m at 5N 78E)
    _, _, z = t.transform(lon, lat, np.zeros_like(lon))
    z = np.asarray(z, dtype=np.float64)
    bad = ~np.isfinite(z) | (np.abs(z) > 1e3)
    if np.any(bad & np.isfinite(lon) & np.isfinite(lat)):
        raise InputError(f"{path}: geoid undulation unavailable at {int(bad.sum())} point(s)")
    z[bad] = np.nan
    return z


def geoid_to_ellipsoid(lon, lat, H):
    """Geoid (EGM96 orthometric) heights H to WGS84 ellipsoidal heights h = H + N."""
    return np.asarray(H, dtype=np.float64) + geoid_undulation(lon, lat)


def ellipsoid_to_geoid(lon, lat, h):
    """WGS84 ellipsoidal heights h to EGM96 geoid heights H = h - N."""
    return np.asarray(h, dtype=np.float64) - geoid_undulation(lon, lat)


# --------------------------------------------------------------------------- rays


def intersect_height(origin, direction, h, iterations: int = 6):
    """Intersect rays with the surface of constant ellipsoidal height ``h``.

    Parameters
    ----------
    origin, direction : array_like, shape (..., 3)
        ECEF ray origins (m) and directions (need not be unit vectors). The near-side
        intersection along ``+direction`` is returned.
    h : array_like
        Ellipsoidal height (m) of the surface, broadcast against the rays.

    Returns
    -------
    points : ndarray (..., 3)
        ECEF intersection points, NaN where the ray misses.

    Notes
    -----
    The first guess intersects the ellipsoid with semi-axes ``(a + h, b + h)`` in closed form
    (Bettemir thesis Eq. 4.32-4.36, with the erratum of its root fixed: with
    ``alpha s^2 + 2 beta s + gamma = 0`` the near root is
    ``(-beta - sqrt(beta^2 - alpha gamma))/alpha``). That surface is not exactly at height ``h``, so
    Newton steps along the ray on the true geodetic height follow (the derivative is the ray's
    component on the local up vector).
    """
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    h = np.asarray(h, dtype=np.float64)
    o, d = np.broadcast_arrays(o, d)
    h = np.broadcast_to(h, o.shape[:-1])
    ah, bh = A + h, B + h
    alpha = (d[..., 0] ** 2 + d[..., 1] ** 2) / ah**2 + d[..., 2] ** 2 / bh**2
    beta = (d[..., 0] * o[..., 0] + d[..., 1] * o[..., 1]) / ah**2 + d[..., 2] * o[..., 2] / bh**2
    gamma = (o[..., 0] ** 2 + o[..., 1] ** 2) / ah**2 + o[..., 2] ** 2 / bh**2 - 1.0
    disc = beta**2 - alpha * gamma
    with np.errstate(invalid="ignore"):
        s = (-beta - np.sqrt(disc)) / alpha
    s = np.where(s > 0, s, np.nan)  # the surface must lie ahead of the origin
    for _ in range(iterations):
        p = o + s[..., None] * d
        lon, lat, hp = ecef_to_geodetic(p[..., 0], p[..., 1], p[..., 2])
        up = enu_basis(lon, lat)[..., 2, :]
        dh_ds = np.sum(up * d, axis=-1)
        step = (hp - h) / dh_ds
        s = s - step
        if np.all(~np.isfinite(step) | (np.abs(step) < 1e-5)):
            break
    p = o + s[..., None] * d
    p[~np.isfinite(s)] = np.nan
    return p


def metres_per_degree(lat):
    """Length in metres of one degree of longitude and of latitude at ``lat`` (degrees, WGS84).

    Returns
    -------
    (m_per_deg_lon, m_per_deg_lat) : ndarray float64
    """
    phi = np.radians(np.asarray(lat, dtype=np.float64))
    w = np.sqrt(1.0 - E2 * np.sin(phi) ** 2)
    n = A / w  # prime vertical radius
    m = A * (1.0 - E2) / w**3  # meridian radius
    return n * np.cos(phi) * np.pi / 180.0, m * np.pi / 180.0
