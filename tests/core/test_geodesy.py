import numpy as np
import pytest
import rasterio

from stereodem.core import geodesy as g
from stereodem.core.errors import CRSError


def test_ecef_round_trip_and_known_point():
    # the equator/Greenwich point on the ellipsoid is (a, 0, 0)
    x, y, z = g.geodetic_to_ecef(0.0, 0.0, 0.0)
    assert (x, y, z) == pytest.approx((g.A, 0.0, 0.0), abs=1e-6)
    x, y, z = g.geodetic_to_ecef(0.0, 90.0, 0.0)
    assert z == pytest.approx(g.B, abs=1e-6)
    rng = np.random.default_rng(1)
    # terrain heights: micrometre exact
    lon, lat, h = (
        rng.uniform(-180, 180, 1000),
        rng.uniform(-89, 89, 1000),
        rng.uniform(-500, 9e3, 1000),
    )
    lon2, lat2, h2 = g.ecef_to_geodetic(*g.geodetic_to_ecef(lon, lat, h))
    assert np.abs(lon2 - lon).max() < 1e-10 and np.abs(lat2 - lat).max() < 1e-10
    assert np.abs(h2 - h).max() < 1e-5
    # orbit heights: PROJ's closed-form inverse is good to about 1 cm (it is only used for
    # reporting satellite positions, never inside the ground geometry)
    h = rng.uniform(4e5, 9e5, 1000)
    lon2, lat2, h2 = g.ecef_to_geodetic(*g.geodetic_to_ecef(lon, lat, h))
    assert np.abs(h2 - h).max() < 0.01


def test_enu_round_trip_and_axes():
    lon0, lat0, h0 = 40.4, 39.6, 1500.0
    # 100 m straight up from the origin is (0, 0, 100) in ENU
    x, y, z = g.geodetic_to_ecef(lon0, lat0, h0 + 100.0)
    e, n, u = g.ecef_to_enu(x, y, z, lon0, lat0, h0)
    assert (float(e), float(n), float(u)) == pytest.approx((0, 0, 100), abs=1e-6)
    # a point slightly north has positive n
    x, y, z = g.geodetic_to_ecef(lon0, lat0 + 1e-3, h0)
    e, n, u = g.ecef_to_enu(x, y, z, lon0, lat0, h0)
    assert n > 100 and abs(e) < 1e-6
    xb, yb, zb = g.enu_to_ecef(e, n, u, lon0, lat0, h0)
    assert np.allclose([xb, yb, zb], [x, y, z], atol=1e-6)


@pytest.mark.parametrize(
    "lon,lat,epsg",
    [
        (40.4, 39.6, 32637),
        (55.7, -21.2, 32740),
        (-121.7, 46.8, 32610),
        (5.0, 60.0, 32632),
        (15.0, 78.0, 32633),
        (-180.0, 0.0, 32601),
    ],
)
def test_utm_zone(lon, lat, epsg):
    assert g.utm_epsg(lon, lat) == epsg


def test_utm_zone_of_points_across_the_antimeridian():
    """Points on both sides of 180 (a Kamchatka or Alaska scene's points, longitudes in
    -180..180) are near 180, not at their arithmetic mean 0 E: zones 60 or 1, not 31 (the
    grid of ``stereo.grid.grid_points`` was laid in zone 31 and zone 40)."""
    assert g.utm_epsg([179.95, -179.99, 179.9], [65.0, 65.0, 65.0]) == 32660
    assert g.utm_epsg([-179.95, 179.99, -179.9], [65.0, 65.0, 65.0]) == 32601
    assert g.utm_epsg([np.nan, 179.9, -179.95], [65.0, 65.0, 65.0]) == 32660
    assert g.utm_epsg(np.array([40.3, 40.5]), np.array([39.5, 39.7])) == 32637
    assert np.allclose(g.lon_beside([-179.99, 179.0, 540.0], 179.9), [180.01, 179.0, 180.0])


def test_utm_zone_bad_input():
    """A clear error, and no NumPy warning before it (all-NaN coordinates)."""
    with pytest.raises(CRSError):
        g.utm_epsg(np.nan, 10)


def _grid_node(lon, lat):
    with rasterio.open(g.egm96_path()) as d:
        r, c = d.index(lon, lat)
        return float(d.read(1)[r, c])


def test_egm96_undulation_known_values():
    # EGM96 at 0N 0E is +17.16 m (SOURCES.md); in eastern Turkey about +17 m as well; in the
    # Indian Ocean low about -100 m
    assert g.geoid_undulation(0.0, 0.0) == pytest.approx(17.16, abs=0.01)
    # the Indian Ocean low, and values read directly from the GTX grid node with rasterio
    assert g.geoid_undulation(78.0, 5.0) == pytest.approx(-104.683, abs=0.01)
    assert g.geoid_undulation(40.5, 39.5) == pytest.approx(_grid_node(40.5, 39.5), abs=1e-3)
    assert g.geoid_undulation(-121.75, 46.75) == pytest.approx(_grid_node(-121.75, 46.75), abs=1e-3)
    lon, lat, H = np.array([40.4, 55.7]), np.array([39.6, -21.2]), np.array([2000.0, 2300.0])
    h = g.geoid_to_ellipsoid(lon, lat, H)
    assert np.allclose(g.ellipsoid_to_geoid(lon, lat, h), H, atol=1e-9)
    assert np.allclose(h - H, g.geoid_undulation(lon, lat))


def test_intersect_height_is_exact():
    rng = np.random.default_rng(3)
    lon = rng.uniform(-179, 179, 200)
    lat = rng.uniform(-80, 80, 200)
    o = np.stack(g.geodetic_to_ecef(lon, lat, np.full(200, 700e3)), -1)
    # oblique rays towards points 100 km away at various heights
    tgt = np.stack(g.geodetic_to_ecef(lon + 0.5, lat + 0.3, np.zeros(200)), -1)
    for h in (-500.0, 0.0, 2500.0, 9000.0):
        p = g.intersect_height(o, tgt - o, h)
        _, _, hp = g.ecef_to_geodetic(p[:, 0], p[:, 1], p[:, 2])
        assert np.abs(hp - h).max() < 1e-4
        # the point lies on the ray
        d = (tgt - o) / np.linalg.norm(tgt - o, axis=1, keepdims=True)
        v = p - o
        assert np.abs(np.linalg.norm(np.cross(v, d), axis=1)).max() < 1e-4
    # a ray pointing away from the Earth misses: NaN, not a wrong point
    p = g.intersect_height(o[:1], o[:1], 0.0)
    assert np.isnan(p).all()
