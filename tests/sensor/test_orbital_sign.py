"""Topan (2009) Table 4.3 column L: the +1 in his look vector puts stereo intersections about
1.9e6 m above the terrain along the local vertical; the SPOT Handbook's -1 does not."""

import numpy as np
import pytest

from stereodem.core import geodesy
from stereodem.sensor.geo.intersect import intersect_rays
from stereodem.sensor.models.orbital import TopanLOSModel
from stereodem.sensor.models.pushbroom import PushbroomModel

ZONGULDAK = (31.795, 41.457)  # Topan's test field
TABLE_4_3_L = np.array([1230150.23, 762556.41, 1260608.51])  # H-0 GCP, m (ECEF X, Y, Z RMSE)


@pytest.fixture(scope="module")
def spot_pair():
    """SPOT-5-like cross-track pair at 832 km (tilts +15 / -15.5 deg: B/H about 0.54)."""
    kw = dict(width=1200, height=1200, altitude=832e3, gsd=5.0, line_period=7.52e-4)
    m1 = PushbroomModel.synthetic(*ZONGULDAK, cross_track_tilt_deg=15.0, **kw)
    m2 = PushbroomModel.synthetic(*ZONGULDAK, cross_track_tilt_deg=-15.5, **kw)
    return TopanLOSModel.from_model(m1), TopanLOSModel.from_model(m2)


def _intersect(t1, t2, sign, lon, lat, h):
    c1, r1 = t1.project(lon, lat, h)
    c2, r2 = t2.project(lon, lat, h)
    o1, d1 = t1.with_los_sign(sign).rays(c1, r1)
    o2, d2 = t2.with_los_sign(sign).rays(c2, r2)
    p, _ = intersect_rays(o1, d1, o2, d2)
    return p - np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)


def test_flipped_sign_reproduces_table_4_3_column_L_and_right_sign_avoids_it(spot_pair):
    t1, t2 = spot_pair
    rng = np.random.default_rng(0)
    lon = ZONGULDAK[0] + rng.uniform(-0.02, 0.02, 20)
    lat = ZONGULDAK[1] + rng.uniform(-0.02, 0.02, 20)
    h = rng.uniform(0, 1800, 20)
    wrong = _intersect(t1, t2, +1, lon, lat, h)
    rmse = np.sqrt(np.mean(wrong**2, axis=0))
    # the size and ECEF split of Topan's column L, within 5 %
    assert np.linalg.norm(rmse) == pytest.approx(np.linalg.norm(TABLE_4_3_L), rel=0.05)
    assert np.allclose(rmse, TABLE_4_3_L, rtol=0.05)
    up = geodesy.enu_basis(*ZONGULDAK)[2]
    assert np.mean(wrong @ up / np.linalg.norm(wrong, axis=1)) > 0.999  # straight up
    right = _intersect(t1, t2, -1, lon, lat, h)
    assert np.max(np.linalg.norm(right, axis=1)) < 0.01  # metres
    # and with +1 the model cannot even localise on the ground: its rays point to space
    lo, la = t1.with_los_sign(+1).localize(600.0, 600.0, 0.0)
    assert np.isnan(lo) and np.isnan(la)
