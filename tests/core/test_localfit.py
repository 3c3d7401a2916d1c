"""Local polynomial stand-ins for PROJ (core/localfit.py, geodesy's ``tolerance`` options):
within their tolerance of PROJ on a stereo tile's extent, PROJ itself where they are not."""

import numpy as np
import pytest

from stereodem.core import geodesy as g
from stereodem.core import localfit

N = 60_000  # above localfit.MIN_POINTS


def _tile_points(lon0, lat0, size_deg, seed=0, n=N):
    """Points of a stereo tile: ``size_deg`` square, heights 500..4000 m."""
    rng = np.random.default_rng(seed)
    lon = lon0 + size_deg * rng.random(n)
    lat = lat0 + size_deg * rng.random(n)
    h = 500.0 + 3500.0 * rng.random(n)
    return lon, lat, h


@pytest.mark.parametrize("lon0, lat0", [(-118.2, 36.5), (177.4, -70.0), (5.1, 0.0), (-2.9, 59.8)])
def test_utm_projection_of_a_tile_is_within_its_tolerance_of_proj(lon0, lat0):
    lon, lat, _ = _tile_points(lon0, lat0, 0.1)
    crs = g.utm_crs(lon0 + 0.05, lat0 + 0.05)
    x, y = g.lonlat_to_crs(lon, lat, crs)
    t = g.transformer(4326, crs.to_wkt()).transform
    fit = localfit.fitted(t, (lon, lat), (1e-4, 1e-4))
    assert fit is not None  # a 0.1 degree tile is within reach of a cubic
    assert np.abs(fit[0] - x).max() <= 1e-4
    assert np.abs(fit[1] - y).max() <= 1e-4
    xa, ya = g.lonlat_to_crs(lon, lat, crs, tolerance=1e-4)
    assert np.array_equal(xa, fit[0]) and np.array_equal(ya, fit[1])


def test_ecef_to_geodetic_of_a_tile_is_within_its_tolerance_of_proj():
    lon, lat, h = _tile_points(86.9, 27.9, 0.08)
    x, y, z = g.geodetic_to_ecef(lon, lat, h)
    lon2, lat2, h2 = g.ecef_to_geodetic(x, y, z, tolerance_m=1e-4)
    lon1, lat1, h1 = g.ecef_to_geodetic(x, y, z)
    assert not np.array_equal(h2, h1)  # the polynomial was used ...
    deg = 1e-4 / (np.pi / 180 * g.A)
    assert np.abs(lon2 - lon1).max() <= deg  # ... and is within 0.1 mm of PROJ
    assert np.abs(lat2 - lat1).max() <= deg
    assert np.abs(h2 - h1).max() <= 1e-4


def test_proj_runs_where_the_polynomial_would_miss_the_tolerance():
    # a 20 degree extent: a cubic is metres off a UTM projection there
    lon, lat, _ = _tile_points(-130.0, 30.0, 20.0)
    crs = g.utm_crs(-120.0, 40.0)
    t = g.transformer(4326, crs.to_wkt()).transform
    assert localfit.fitted(t, (lon, lat), (1e-4, 1e-4)) is None
    xa, ya = g.lonlat_to_crs(lon, lat, crs, tolerance=1e-4)
    x, y = g.lonlat_to_crs(lon, lat, crs)
    assert np.array_equal(xa, x) and np.array_equal(ya, y)
    # and one blunder (a ray intersection 300 km up) puts a tile out of reach as well
    lon, lat, h = _tile_points(10.0, 45.0, 0.05)
    h[7] = 3e5
    p = g.geodetic_to_ecef(lon, lat, h)
    assert np.array_equal(g.ecef_to_geodetic(*p, tolerance_m=1e-4)[2], g.ecef_to_geodetic(*p)[2])


def test_few_points_and_non_finite_points():
    lon, lat, _ = _tile_points(10.0, 45.0, 0.05, n=localfit.MIN_POINTS - 1)
    crs = g.utm_crs(10.0, 45.0)
    t = g.transformer(4326, crs.to_wkt()).transform
    assert localfit.fitted(t, (lon, lat), (1e-4, 1e-4)) is None  # PROJ: the fit would not pay
    lon, lat, h = _tile_points(10.0, 45.0, 0.05)
    x, y, z = g.geodetic_to_ecef(lon, lat, h)
    x[[3, 99]] = np.nan  # parallel rays
    out = g.ecef_to_geodetic(x, y, z, tolerance_m=1e-4)
    ref = g.ecef_to_geodetic(x, y, z)
    for a, b in zip(out, ref):
        assert not np.isfinite(a[[3, 99]]).any()
        ok = np.isfinite(b)
        assert np.isfinite(a[ok]).all() and np.abs(a[ok] - b[ok]).max() < 1e-4
    assert localfit.fitted(t, (np.full(N, np.nan), np.full(N, np.nan)), (1.0, 1.0)) is None


def test_a_point_gets_the_same_value_whatever_else_is_converted_with_it():
    # the fit depends on the bounding box only, and the evaluation of a point on nothing
    # else: the same points in another order give the same values (bit for bit)
    lon, lat, h = _tile_points(-70.0, -33.0, 0.07)
    crs = g.utm_crs(-70.0, -33.0)
    x, y = g.lonlat_to_crs(lon, lat, crs, tolerance=1e-4)
    order = np.random.default_rng(3).permutation(N)
    xp, yp = g.lonlat_to_crs(lon[order], lat[order], crs, tolerance=1e-4)
    assert np.array_equal(xp, x[order]) and np.array_equal(yp, y[order])


def test_metres_in_crs():
    assert g.metres_in_crs(1.0, 32611) == 1.0
    assert g.metres_in_crs(1.0, "EPSG:2272") == pytest.approx(1 / 0.3048006096)  # US feet
    deg = g.metres_in_crs(1.0, 4326)
    assert deg == pytest.approx(1 / 111319.49, rel=1e-6)
