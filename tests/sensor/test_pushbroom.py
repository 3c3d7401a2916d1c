"""Pushbroom sensor model, ephemeris/attitude interpolation and the synthetic orbit builder."""

import json
import time

import numpy as np
import pytest
from numpy.polynomial import Polynomial
from scipy.spatial.transform import Rotation

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import SensorModelError
from stereodem.sensor.geo.rotations import body_to_orbital, inertial_velocity
from stereodem.sensor.io.sidecar import load_model, model_from_dict, model_to_dict
from stereodem.sensor.models import pushbroom
from stereodem.sensor.models.ephemeris import Attitude, CircularOrbit, Ephemeris, _LagrangeTable
from stereodem.sensor.models.pushbroom import PARAMETERS, DetectorArray, PushbroomModel

# ---------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def nadir():
    return PushbroomModel.synthetic(40.4, 39.6, width=2000, height=2200)


@pytest.fixture(scope="module")
def backward():
    return PushbroomModel.synthetic(40.4, 39.6, width=2500, height=2800, along_track_tilt_deg=-27.6)


@pytest.fixture(scope="module")
def pair():
    return PushbroomModel.synthetic_pair(
        -121.8, 47.0, width=4100, height=4200, backward_width=5000, backward_height=5400
    )


def _image_samples(model, n, seed):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0, model.width - 1, n)
    r = rng.uniform(0, model.height - 1, n)
    # include the corners and the extreme heights explicitly
    c = np.concatenate([c, [0, model.width - 1, 0, model.width - 1]])
    r = np.concatenate([r, [0, 0, model.height - 1, model.height - 1]])
    h = np.concatenate([rng.uniform(-500, 9000, n), [-500, 9000, 9000, -500]])
    return c, r, h


# ---------------------------------------------------------------------------- ephemeris


def test_lagrange_reproduces_degree7_polynomial_and_its_derivative():
    t = np.arange(0.0, 20.0, 1.3)
    poly = [
        Polynomial(np.random.default_rng(k).normal(size=8) * 10.0 ** (3 - np.arange(8)))
        for k in range(3)
    ]
    pos = np.stack([p(t) for p in poly], -1)
    eph = Ephemeris(t, pos)
    tq = np.linspace(-1.0, 21.0, 301)  # includes short extrapolation
    want = np.stack([p(tq) for p in poly], -1)
    want_v = np.stack([p.deriv()(tq) for p in poly], -1)
    scale = np.abs(want).max()
    assert np.max(np.abs(eph.position(tq) - want)) < 1e-9 * scale
    assert np.max(np.abs(eph.velocity(tq) - want_v)) < 1e-8 * np.abs(want_v).max()
    np.testing.assert_array_equal(eph.position(tq.reshape(7, 43)).shape, (7, 43, 3))


def test_ephemeris_interpolates_circular_orbit():
    orbit = CircularOrbit(geodesy.A + 705e3, np.radians(98.2), 0.3, 2.0)
    eph = orbit.ephemeris(-60.0, 60.0, 1.0)
    t = np.random.default_rng(0).uniform(-55, 55, 500)
    r, v = orbit.state(t)
    pe, ve = eph.state(t)
    assert np.max(np.linalg.norm(pe - r, axis=-1)) < 1e-4  # 0.1 mm
    assert np.max(np.linalg.norm(ve - v, axis=-1)) < 1e-6
    # velocity from the derivative of the positions when no velocity is given
    eph2 = Ephemeris(eph.times, eph.positions)
    assert np.max(np.linalg.norm(eph2.velocity(t) - v, axis=-1)) < 1e-4
    # nodes are reproduced exactly
    assert np.max(np.abs(eph.position(eph.times) - eph.positions)) < 1e-6
    # circular speed: |v_inertial| = sqrt(GM / a)

    speed = np.linalg.norm(inertial_velocity(r, v), axis=-1)
    np.testing.assert_allclose(speed, np.sqrt(geodesy.GM / orbit.radius), rtol=1e-12)


@pytest.mark.parametrize(
    "times, pos",
    [
        ([0.0, 1.0, 1.0], np.zeros((3, 3))),
        ([0.0, 1.0, np.nan], np.zeros((3, 3))),
        ([0.0, 1.0, 2.0], np.zeros((3, 2))),
        ([0.0, 1.0, 2.0], np.array([[0, 0, 0], [0, np.nan, 0], [0, 0, 0]], float)),
        ([0.0], np.zeros((1, 3))),
    ],
)
def test_ephemeris_rejects_bad_samples(times, pos):
    with pytest.raises(SensorModelError):
        Ephemeris(times, pos)


def test_attitude_angles_and_quaternions():
    t = np.linspace(0, 10, 11)
    ang = 1e-3 * np.stack([np.sin(t), np.cos(0.5 * t), 0.1 * t], -1)
    att = Attitude(t, ang)
    np.testing.assert_allclose(
        att.matrix(t), body_to_orbital(ang[:, 0], ang[:, 1], ang[:, 2]), atol=1e-15
    )
    mid = att.angles_at(np.array([0.5, 5.5]))
    assert np.all(
        np.abs(mid - 1e-3 * np.stack([np.sin([0.5, 5.5]), np.cos([0.25, 2.75]), [0.05, 0.55]], -1))
        < 2e-5
    )
    q = Rotation.from_matrix(body_to_orbital(ang[:, 0], ang[:, 1], ang[:, 2])).as_quat()
    attq = Attitude(t, quaternions=q)
    np.testing.assert_allclose(attq.matrix(t), att.matrix(t), atol=1e-12)
    tq = np.linspace(0, 10, 37)
    true = 1e-3 * np.stack([np.sin(tq), np.cos(0.5 * tq), 0.1 * tq], -1)
    want = body_to_orbital(true[:, 0], true[:, 1], true[:, 2])
    # both interpolants follow the true attitude to the spline error (~2e-5 rad here)
    assert np.max(np.abs(attq.matrix(tq) - want)) < 3e-5
    assert np.max(np.abs(att.matrix(tq) - want)) < 3e-5
    m = attq.matrix(tq)
    np.testing.assert_allclose(
        m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12
    )
    const = Attitude.fixed(pitch=0.01)
    np.testing.assert_allclose(
        const.matrix(np.zeros(4)), np.broadcast_to(body_to_orbital(0, 0.01, 0), (4, 3, 3))
    )
    with pytest.raises(SensorModelError):
        Attitude(t, ang, quaternions=q)
    with pytest.raises(SensorModelError):
        Attitude(t, quaternions=2 * q)


# ---------------------------------------------------------------------------- detectors


def test_detector_table_interpolation_and_inversion():
    cols = np.linspace(0, 4100, 11)
    vec = np.stack(
        [np.full(11, 4.7e-4), 0.192 - 2.1e-5 * cols + 1e-10 * (cols - 2050) ** 2, np.ones(11)], -1
    )
    det = DetectorArray.from_sight_vectors(vec / np.linalg.norm(vec, axis=1, keepdims=True), cols)
    tx, ty = det.tangents(cols)
    np.testing.assert_allclose(ty, vec[:, 1], atol=1e-15)
    np.testing.assert_allclose(
        det.directions(cols), vec / np.linalg.norm(vec, axis=1, keepdims=True), atol=1e-15
    )
    q = np.random.default_rng(3).uniform(-50, 4150, 1000)
    _, tyq = det.tangents(q)
    assert np.max(np.abs(det.column(tyq) - q)) < 1e-9
    # look angles as polynomials of the column
    det2 = DetectorArray.from_look_angles(
        Polynomial([1e-3, 1e-8]), Polynomial([0.1, -2e-5]), width=4100
    )
    txq, tyq = det2.tangents(q)
    np.testing.assert_allclose(txq, np.tan(1e-3 + 1e-8 * q), rtol=1e-14)
    assert np.max(np.abs(det2.column(tyq) - q)) < 1e-9
    # row-dependent tables blend linearly between rows
    tab = np.stack([vec, vec + np.array([0.0, 0.01, 0.0])])
    det3 = DetectorArray.from_sight_vectors(tab, cols, rows=np.array([0.0, 400.0]))
    np.testing.assert_allclose(det3.tangents(cols, 200.0)[1], vec[:, 1] + 0.005, atol=1e-15)
    assert np.max(np.abs(det3.column(det3.tangents(q, 100.0)[1], 100.0) - q)) < 1e-9
    with pytest.raises(SensorModelError):  # cross-track angle not monotonic
        DetectorArray.from_look_angles(0.0, Polynomial([0.0, -1e-3, 1e-6]), width=4000)
    with pytest.raises(SensorModelError):  # polynomial without a detector count
        DetectorArray.from_look_angles(0.0, Polynomial([0.0, -1e-3]))
    # per-detector arrays of look angles
    psi_y = np.arctan(0.1 - 2e-5 * np.arange(500.0))
    det4 = DetectorArray.from_look_angles(np.zeros(500), psi_y)
    np.testing.assert_allclose(det4.column(np.tan(psi_y)), np.arange(500.0), atol=1e-9)


# ---------------------------------------------------------------------------- synthetic models


def test_synthetic_geometry(nadir, backward):
    for m in (nadir, backward):
        lon, lat = m.center_lonlat()
        assert abs(lon - 40.4) < 1e-9 and abs(lat - 39.6) < 1e-9
    # nadir GSD across track = 15 m; along track = ground speed * line period (~15 m)
    c0, r0 = (nadir.width - 1) / 2, (nadir.height - 1) / 2
    lon, lat = nadir.localize([c0, c0 + 1, c0], [r0, r0, r0 + 1], 0.0)
    p = np.stack(geodesy.geodetic_to_ecef(lon, lat, np.zeros(3)), -1)
    assert abs(np.linalg.norm(p[1] - p[0]) - 15.0) < 0.02
    assert 14.0 < np.linalg.norm(p[2] - p[0]) < 15.5
    # descending pass: rows run south, columns east (north-up image)
    assert lat[2] < lat[0] and lon[1] > lon[0]
    # the backward view looks 27.6 deg back: satellite is ahead (south) of the ground point
    o, d = backward.rays(c0, (backward.height - 1) / 2)
    x, y, z = geodesy.geodetic_to_ecef(40.4, 39.6, 0.0)
    up = geodesy.enu_basis(40.4, 39.6)[2]
    off_nadir = np.degrees(np.arccos(-d @ (o / np.linalg.norm(o))))
    assert 27.0 < off_nadir < 28.0
    v = o - [x, y, z]
    zenith = np.degrees(np.arccos(v @ up / np.linalg.norm(v)))
    # incidence at the ground = look angle + Earth-central angle (~3.4 deg at 705 km)
    assert geodesy.ecef_to_geodetic(*o)[1] < 39.6 and 30.0 < zenith < 32.0


@pytest.mark.parametrize("which", ["nadir", "backward"])
def test_round_trips_synthetic(which, nadir, backward):
    m = nadir if which == "nadir" else backward
    c, r, h = _image_samples(m, 4000, seed=1)
    lon, lat = m.localize(c, r, h)
    cc, rr = m.project(lon, lat, h)
    assert np.max(np.abs(cc - c)) < 1e-6 and np.max(np.abs(rr - r)) < 1e-6
    # ground -> image -> ground, points spread over the scene at random heights
    rng = np.random.default_rng(2)
    lon2, lat2 = m.localize(
        rng.uniform(0, m.width - 1, 3000), rng.uniform(0, m.height - 1, 3000), 0.0
    )
    h2 = rng.uniform(-500, 9000, lon2.size)
    c2, r2 = m.project(lon2, lat2, h2)
    lon3, lat3 = m.localize(c2, r2, h2)
    p2 = np.stack(geodesy.geodetic_to_ecef(lon2, lat2, h2), -1)
    p3 = np.stack(geodesy.geodetic_to_ecef(lon3, lat3, h2), -1)
    assert np.max(np.linalg.norm(p3 - p2, axis=-1)) < 1e-3
    # the projected point lies on the ray of its pixel (exact scan-plane solution)
    o, d = m.rays(c2, r2)
    v = p2 - o
    miss = np.linalg.norm(v - np.sum(v * d, -1, keepdims=True) * d, axis=-1)
    assert np.max(miss) < 1e-3


def test_pair_on_one_orbit(pair):
    nad, back = pair
    assert nad.orbit is back.orbit
    for m in pair:
        lon, lat = m.center_lonlat()
        assert abs(lon + 121.8) < 1e-9 and abs(lat - 47.0) < 1e-9
    lag = back.reference_time - nad.reference_time
    assert 50.0 < lag < 60.0  # ASTER: ~55 s
    assert 0.5 < back.cross_track_tilt_deg < 2.5  # Earth rotation during the lag
    # same orbit: the backward ephemeris agrees with the nadir one where both are sampled
    t = np.linspace(back.ephemeris.times[0] + 5, nad.ephemeris.times[-1] - 5, 20)
    assert (
        np.max(np.linalg.norm(back.ephemeris.position(t) - nad.ephemeris.position(t), axis=-1))
        < 1e-3
    )
    # stereo convergence angle ~ 30 deg at the scene centre; the nadir footprint falls in the
    # backward image (its wider, longer swath)
    o1, d1 = nad.rays((nad.width - 1) / 2, (nad.height - 1) / 2)
    o2, d2 = back.rays((back.width - 1) / 2, (back.height - 1) / 2)
    assert 27.0 < np.degrees(np.arccos(d1 @ d2)) < 34.0
    cb, rb = back.project(*nad.footprint(0.0, 5), 0.0)
    assert np.all((cb > 0) & (cb < back.width - 1) & (rb > 0) & (rb < back.height - 1))
    c, r, h = _image_samples(back, 2000, seed=4)
    cc, rr = back.project(*back.localize(c, r, h), h)
    assert np.max(np.abs(cc - c)) < 1e-6 and np.max(np.abs(rr - r)) < 1e-6


def test_project_of_many_points_is_exact(nadir):
    c, r, h = _image_samples(nadir, 100_000, seed=5)
    lon, lat = nadir.localize(c, r, h)
    nadir.project(lon[:10], lat[:10], h[:10])  # builds the first-guess fit
    t = time.perf_counter()
    cc, rr = nadir.project(lon, lat, h)
    elapsed = time.perf_counter() - t
    print(f"project of 1e5 points: {elapsed:.3f} s (timed, not asserted: benchmarks/ hold speed)")
    assert np.max(np.abs(rr - r)) < 1e-6


def test_localize_dem_drm(nadir):
    dem = DEM.bundled()
    c, r = np.meshgrid(np.linspace(0, nadir.width - 1, 30), np.linspace(0, nadir.height - 1, 30))
    res = nadir.localize_dem(c, r, dem)
    assert res.converged.all()
    print(f"DRM mean iterations {res.mean_iterations:.2f}, max {res.iterations.max()}")
    assert res.mean_iterations <= 5
    assert np.nanmin(res.h) > 1000  # real terrain (ellipsoidal heights)
    cc, rr = nadir.project(res.lon, res.lat, res.h)
    assert np.max(np.hypot(cc - c, rr - r)) < 1e-3


# -------------------------------------------------------------------------- frame chain, parameters


def test_attitude_tilt_and_bias_compose_consistently(nadir):
    c, r = np.array([0.0, 999.5, 1999.0]), np.array([0.0, 1100.0, 2199.0])
    kw = dict(
        width=nadir.width,
        height=nadir.height,
        ephemeris=nadir.ephemeris,
        detectors=nadir.detectors,
        line_period=nadir.line_period,
        t0=nadir.t0,
    )
    pitch = np.radians(2.0)
    by_tilt = PushbroomModel(along_track_tilt_deg=2.0, **kw)
    by_attitude = PushbroomModel(attitude=Attitude.fixed(pitch=pitch), **kw)
    by_bias = nadir.with_parameters(pitch_bias=pitch)
    d0 = by_tilt.rays(c, r)[1]
    for m in (by_attitude, by_bias):
        np.testing.assert_allclose(m.rays(c, r)[1], d0, atol=1e-14)
    # a forward pitch looks ahead: its rays point more along the flight direction
    x_axis = nadir.ephemeris.velocity(nadir.line_time(r))
    assert np.all(np.sum(d0 * x_axis, -1) > np.sum(nadir.rays(c, r)[1] * x_axis, -1))


def test_parameters_hook(nadir):
    p = nadir.parameters()
    assert list(p) == list(PARAMETERS) and all(v == 0.0 for v in p.values())
    moved = nadir.with_parameters(
        pitch_bias=1e-4, position_offset_y=20.0, look_scale=1e-4, time_offset=0.01
    )
    assert nadir.parameters()["pitch_bias"] == 0.0 and moved.parameters()["pitch_bias"] == 1e-4
    lon, lat = nadir.localize([300.0, 1500.0], [200.0, 2000.0], 1000.0)
    c0, r0 = nadir.project(lon, lat, 1000.0)
    c1, r1 = moved.project(lon, lat, 1000.0)
    # pitch 1e-4 rad x ~710 km range / 15 m ~ 4.7 lines, plus 0.01 s / 2.2 ms ~ 4.5 lines, both
    # seeing the ground earlier; 20 m to the right ~ 1.3 columns towards +col (east)
    assert np.all((r0 - r1 > 8.0) & (r0 - r1 < 10.5))
    assert np.all((c1 - c0 > 0.8) & (c1 - c0 < 1.6))
    c2, r2 = moved.project(*moved.localize(c1, r1, 1000.0), 1000.0)
    assert np.max(np.abs(c2 - c1)) < 1e-6 and np.max(np.abs(r2 - r1)) < 1e-6
    with pytest.raises(SensorModelError, match="unknown parameter"):
        nadir.with_parameters(focal=1.0)


def test_time_varying_attitude_round_trip(nadir):
    t = nadir.ephemeris.times
    ang = 2e-4 * np.stack([np.sin(0.7 * t), np.cos(0.3 * t), np.sin(0.1 * t)], -1)
    m = PushbroomModel(
        width=nadir.width,
        height=nadir.height,
        ephemeris=nadir.ephemeris,
        detectors=nadir.detectors,
        line_period=nadir.line_period,
        t0=nadir.t0,
        attitude=Attitude(t, ang),
    )
    c, r, h = _image_samples(m, 2000, seed=6)
    cc, rr = m.project(*m.localize(c, r, h), h)
    assert np.max(np.abs(cc - c)) < 1e-6 and np.max(np.abs(rr - r)) < 1e-6


def test_bad_input(nadir):
    with pytest.raises(SensorModelError, match="non-finite"):
        nadir.project([40.4, np.nan], [39.6, 39.6], 0.0)
    with pytest.raises(SensorModelError, match="non-finite"):
        nadir.localize([1.0], [np.inf], 0.0)
    with pytest.raises(SensorModelError):
        PushbroomModel.synthetic(0.0, 85.0, width=10, height=10)  # latitude not overflown
    with pytest.raises(SensorModelError):
        PushbroomModel(
            width=10,
            height=10,
            ephemeris=nadir.ephemeris,
            detectors=nadir.detectors,
            line_period=-1.0,
        )


def test_serialisation_round_trip(nadir):
    t = nadir.ephemeris.times
    att = Attitude(t, 1e-4 * np.stack([np.sin(t), np.cos(t), 0 * t], -1))
    models = [
        nadir.with_parameters(roll_bias=1e-5),
        PushbroomModel(
            width=500,
            height=400,
            ephemeris=nadir.ephemeris,
            line_period=nadir.line_period,
            t0=nadir.t0,
            attitude=att,
            cross_track_tilt_deg=3.0,
            detectors=DetectorArray.from_look_angles(
                Polynomial([1e-3, 1e-8]), Polynomial([0.01, -2e-5]), width=500
            ),
        ),
    ]
    for m in models:
        d = json.loads(json.dumps(model_to_dict(m)))
        assert d["type"] == "pushbroom"
        back = model_from_dict(d)
        assert type(back) is PushbroomModel and back.parameters() == m.parameters()
        c, r = np.array([0.0, 250.5, 499.0]), np.array([3.0, 200.0, 399.0])
        np.testing.assert_array_equal(back.localize(c, r, 100.0), m.localize(c, r, 100.0))
    assert (
        model_from_dict(json.loads(json.dumps(model_to_dict(nadir)))).orbit.raan == nadir.orbit.raan
    )


@pytest.mark.parametrize(
    "edit, match",
    [
        (dict(cross_track_tilt_deg=float("nan")), "cross_track_tilt_deg must be finite, got nan"),
        (dict(along_track_tilt_deg=float("inf")), "along_track_tilt_deg must be finite"),
        (dict(t0=float("nan")), "t0 must be finite"),
        (dict(line_period="fast"), "line_period must be a number, got 'fast'"),
        (dict(type=["pushbroom"]), r"unknown model type \['pushbroom'\]"),
        (dict(ephemeris=None), "missing key 'ephemeris'"),
    ],
)
def test_garbled_sidecar_names_the_file_and_the_field(nadir, tmp_path, edit, match):
    """A hand-edited ``<stem>.model.json``: a NaN tilt or t0 was accepted (ortho then blamed
    the DEM for a footprint of NaN, dem reported "non-finite ground coordinates"), a list as
    the type raised a TypeError traceback, a missing key read "garbled model ('ephemeris')"."""
    d = model_to_dict(nadir)
    d.update(edit)
    d = {k: v for k, v in d.items() if v is not None}
    path = tmp_path / "img.model.json"
    path.write_text(json.dumps(d))
    with pytest.raises(SensorModelError, match=f"img.model.json: .*{match}"):
        load_model(path)


def test_pair_with_two_tilts():
    fwd, bwd = PushbroomModel.synthetic_pair(
        40.4, 39.6, width=800, height=900, first_tilt_deg=20.0, backward_tilt_deg=-20.0
    )
    assert fwd.orbit is bwd.orbit and fwd.along_track_tilt_deg == 20.0
    for m in (fwd, bwd):
        lon, lat = m.center_lonlat()
        assert abs(lon - 40.4) < 1e-9 and abs(lat - 39.6) < 1e-9
    assert 70.0 < bwd.reference_time - fwd.reference_time < 95.0
    o1, d1 = fwd.rays(399.5, 449.5)
    o2, d2 = bwd.rays(399.5, 449.5)
    assert 40.0 < np.degrees(np.arccos(d1 @ d2)) < 48.0


def test_lagrange_by_window_equals_gathered_evaluation():
    """Many times in few windows (a tile's lines) take the per-window path: the values and
    derivatives are those of the gathered-coefficient evaluation, bit for bit."""
    rng = np.random.default_rng(0)
    ts = np.cumsum(rng.uniform(0.9, 1.1, 40))
    tab = _LagrangeTable(ts, rng.normal(0, 7e6, (40, 3)), 8)
    t = rng.uniform(5.0, 9.0, 5000)  # 4-5 windows: the per-window path
    w = tab._window(t)
    assert np.unique(w).size <= 16
    x = (t - tab.centre[w]) / tab.half[w]
    c = tab.coef[w]
    val = c[:, -1, :].copy()
    for j in range(tab.k - 2, -1, -1):
        val = val * x[:, None] + c[:, j, :]
    val = val + tab.mean[w]
    der = np.zeros_like(val)
    for j in range(tab.k - 1, 0, -1):
        der = der * x[:, None] + j * c[:, j, :]
    der = der / tab.half[w][:, None]
    got_val, got_der = tab.evaluate(t.reshape(50, 100), derivative=True)
    np.testing.assert_array_equal(got_val.reshape(-1, 3), val)
    np.testing.assert_array_equal(got_der.reshape(-1, 3), der)
    np.testing.assert_array_equal(tab.evaluate(t), val)


def test_pose_table_rays_match_exact_pose(nadir, monkeypatch):
    """The matched pixels of a tile (many fractional rows over few lines) take their pose from
    a per-line table interpolated linearly (``_pose``): against the pose evaluated at every
    row (``_exact_pose``) the rays' origins agree to < 1e-4 m and their directions to
    < 1e-10 rad without jitter; with an attitude jitter of 20 urad at 5 Hz (stronger than
    ASTER's) the direction error is the linear-interpolation bound (|angle''| dt^2 / 8,
    ~1e-8 rad) and stays < 1e-3 px (IFOV units), far below the matching noise (~0.1 px)."""
    t = np.arange(nadir.line_time(-50.0), nadir.line_time(nadir.height + 50.0), 0.01)
    jitter = 2e-5 * np.sin(2 * np.pi * 5.0 * t)
    ang = np.stack([jitter + 1e-4 * np.sin(0.7 * t), 0.5 * jitter, 1e-4 * np.cos(0.3 * t)], -1)
    m = PushbroomModel(
        width=nadir.width,
        height=nadir.height,
        ephemeris=nadir.ephemeris,
        detectors=nadir.detectors,
        line_period=nadir.line_period,
        t0=nadir.t0,
        attitude=Attitude(t, ang),
    )
    rng = np.random.default_rng(3)
    n = 60000  # a 512 x 525 tile's worth of matches
    col = rng.uniform(700.0, 1212.0, n)
    row = rng.uniform(900.0, 1425.0, n)
    assert pushbroom._line_table(row) is not None  # the table path is the one tested
    assert pushbroom._line_table(row[:100]) is None  # few rows: evaluated directly
    o, d = m.rays(col, row)
    c_exact, rot_exact = m._exact_pose(row)
    u = m.detectors.directions(col, row)
    d_exact = np.einsum("nij,nj->ni", rot_exact, u)
    d_exact /= np.linalg.norm(d_exact, axis=1, keepdims=True)
    assert np.max(np.linalg.norm(o - c_exact, axis=1)) < 1e-4
    ifov = np.linalg.norm(
        np.diff(m.rays(np.array([1000.0, 1001.0]), np.array([1000.0, 1000.0]))[1], axis=0)
    )
    err = np.linalg.norm(d - d_exact, axis=1)
    bound = 2e-5 * (2 * np.pi * 5.0) ** 2 * m.line_period**2 / 8 * np.sqrt(1.25)
    assert np.max(err) < 1.5 * bound + 1e-12 and np.max(err) < 1e-3 * ifov
    smooth = PushbroomModel(
        width=nadir.width,
        height=nadir.height,
        ephemeris=nadir.ephemeris,
        detectors=nadir.detectors,
        line_period=nadir.line_period,
        t0=nadir.t0,
    )
    c_s, rot_s = smooth._exact_pose(row)
    d_s = np.einsum("nij,nj->ni", rot_s, u)
    d_s /= np.linalg.norm(d_s, axis=1, keepdims=True)
    o_t, d_t = smooth.rays(col, row)
    assert np.max(np.linalg.norm(o_t - c_s, axis=1)) < 1e-4
    assert np.max(np.linalg.norm(d_t - d_s, axis=1)) < 1e-10
    # the image -> ground -> image round trip of the tile's points stays exact
    h = rng.uniform(0.0, 3000.0, n)
    cc, rr = m.project(*m.localize(col, row, h), h)
    assert np.max(np.abs(cc - col)) < 1e-6 and np.max(np.abs(rr - row)) < 1e-6
    # the table path computes the rays by chunks of RAY_CHUNK points: the same values, bit
    # for bit, as in one piece (and for a 2-D array of points)
    assert n > 2 * pushbroom.RAY_CHUNK
    with monkeypatch.context() as mp:
        mp.setattr(pushbroom, "RAY_CHUNK", n)
        o1, d1 = m.rays(col, row)
    np.testing.assert_array_equal(o1, o)
    np.testing.assert_array_equal(d1, d)
    o3, d3 = m.rays(col.reshape(300, 200), row.reshape(300, 200))
    assert o3.shape == d3.shape == (300, 200, 3)
    np.testing.assert_array_equal(d3.reshape(-1, 3), d)
    # spread-out rows (fewer than POSE_TABLE_ROWS_PER_LINE per line) are evaluated directly
    monkeypatch.setattr(pushbroom, "POSE_TABLE_MIN_ROWS", 10**9)
    o2, d2 = m.rays(col, row)
    np.testing.assert_array_equal(o2, c_exact)
