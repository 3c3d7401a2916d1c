import numpy as np
import pytest

from stereodem.core import geodesy as g
from stereodem.core.dem import DEM
from stereodem.sensor.geo.rotations import body_to_orbital
from stereodem.sensor.models.frame import FrameCamera


def bilsat_like(**kw):
    lon0, lat0 = 40.4, 39.6
    north = g.enu_basis(lon0, lat0)[1]
    pos = np.array(g.geodetic_to_ecef(lon0, lat0 - 0.2, 686e3))
    args = dict(
        width=2048,
        height=2048,
        focal_mm=184.0,
        pitch_mm=0.0074,
        k1=3.6e-4,
        k2=-1e-6,
        p1=2e-5,
        p2=-1e-5,
        dx_mm=0.01,
        dy_mm=-0.02,
    )
    args.update(kw)
    return FrameCamera.looking_at(pos, 7500 * north, lon0, lat0, 2000.0, **args)


def test_eq_4_7_matrix():
    w, p, k = 0.1, -0.2, 0.3
    cw, sw, cp, sp, ck, sk = np.cos(w), np.sin(w), np.cos(p), np.sin(p), np.cos(k), np.sin(k)
    eq47 = np.array(
        [
            [ck * cp - sk * sw * sp, -sk * cw, ck * sp + sk * sw * cp],
            [sk * cp + ck * sw * sp, ck * cw, sk * sp - ck * sw * cp],
            [-cw * sp, sw, cw * cp],
        ]
    )
    assert np.abs(body_to_orbital(w, p, k) - eq47).max() < 1e-15


def test_round_trip_whole_image_and_height_range():
    cam = bilsat_like()
    rng = np.random.default_rng(0)
    n = 50000
    col, row = rng.uniform(-0.5, 2047.5, n), rng.uniform(-0.5, 2047.5, n)
    h = rng.uniform(-500, 9000, n)
    lon, lat = cam.localize(col, row, h)
    c2, r2 = cam.project(lon, lat, h)
    assert np.abs(c2 - col).max() < 1e-6 and np.abs(r2 - row).max() < 1e-6
    # ground round trip to 1 mm
    lon2, lat2 = cam.localize(c2, r2, h)
    x1 = np.stack(g.geodetic_to_ecef(lon, lat, h), -1)
    x2 = np.stack(g.geodetic_to_ecef(lon2, lat2, h), -1)
    assert np.linalg.norm(x1 - x2, axis=1).max() < 1e-3


def test_image_axes_orientation():
    """Image up is the flight direction (north here); image right is right of track (east)."""
    cam = bilsat_like(k1=0, k2=0, p1=0, p2=0, dx_mm=0, dy_mm=0)
    lon, lat = cam.localize(
        np.array([1023.5, 1023.5, 1500.0]), np.array([1023.5, 500.0, 1023.5]), 2000.0
    )
    assert lat[1] > lat[0] + 0.05  # up in the image = north
    assert lon[2] > lon[0] + 0.05  # right in the image = east
    # the boresight hits the target
    assert lon[0] == pytest.approx(40.4, abs=1e-9) and lat[0] == pytest.approx(39.6, abs=1e-9)
    assert cam.gsd(2000.0) == pytest.approx(686e3 * 0.0074 / 184.0, rel=0.02)


def test_distortion_moves_corners_as_the_thesis_says():
    """With k1 = 3.6e-4 (Table B.8) the correction shifts corner rays by tens of pixels (notes
    §2.2)."""
    cam = bilsat_like(k2=0, p1=0, p2=0, dx_mm=0, dy_mm=0)
    plain = bilsat_like(k1=0, k2=0, p1=0, p2=0, dx_mm=0, dy_mm=0)
    lon, lat = cam.localize(0.0, 0.0, 1000.0)
    c, r = plain.project(lon, lat, 1000.0)
    shift = np.hypot(c - 0.0, r - 0.0)
    assert 20 < shift < 60


def test_behind_camera_is_nan():
    cam = bilsat_like()
    # a point 5000 km above the target lies behind the (down-looking) camera
    c, r = cam.project(40.4, 39.6, 5.0e6)
    assert np.isnan(c) and np.isnan(r)


def test_drm_on_dem_converges_and_reprojects():
    cam = bilsat_like()
    dem = DEM.bundled()
    rng = np.random.default_rng(5)
    col, row = rng.uniform(0, 2047, 3000), rng.uniform(0, 2047, 3000)
    res = cam.localize_dem(col, row, dem)
    ok = res.converged
    assert ok.mean() > 0.99
    assert res.mean_iterations <= 5
    c2, r2 = cam.project(res.lon[ok], res.lat[ok], res.h[ok])
    assert np.abs(c2 - col[ok]).max() < 1e-3 and np.abs(r2 - row[ok]).max() < 1e-3
    # the point is on the DEM surface to the 0.1 m threshold
    z = dem.sample(res.lon[ok], res.lat[ok])
    assert np.abs(z - res.h[ok]).max() < 0.1


def test_parameters_vector_and_copy():
    cam = bilsat_like()
    p = cam.parameters()
    assert list(p) == list(FrameCamera.PARAMETERS)
    cam2 = cam.with_parameters(roll=cam.roll + 1e-4, z=p["z"] + 10)
    assert cam2.roll == pytest.approx(cam.roll + 1e-4) and cam2.position[2] == pytest.approx(
        p["z"] + 10
    )
    c1, _ = cam.project(40.4, 39.6, 2000.0)
    c2, _ = cam2.project(40.4, 39.6, 2000.0)
    assert abs(c1 - c2) > 0.5
