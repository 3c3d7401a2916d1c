"""Simulated control points for sensor-model adjustment experiments.

A metadata model (what the product header says) and a "truth" model (the same sensor with
ephemeris and attitude biases and drifts) of the simulator's ASTER 3N geometry; ground points
on the bundled DEM seen by the truth at chosen pixels, with Gaussian measurement noise on the
image coordinates. Used by the orbital-model tests and ``benchmarks/bench_topan_sets.py``.
"""

from __future__ import annotations

import functools

import numpy as np

from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.simulation.simulate import aster_geometry_parameters, pushbroom_pair

#: Pointing and position errors of the truth against the metadata (PushbroomModel parameters):
#: about 1.5 px of attitude bias, 0.5 px of attitude drift over the scene, 20 m of position.
TRUTH_ERRORS = dict(
    roll_bias=3e-5,
    pitch_bias=-2e-5,
    yaw_bias=1e-4,
    roll_drift=2e-6,
    pitch_drift=-1.5e-6,
    yaw_drift=5e-6,
    position_offset_x=20.0,
    position_offset_y=-15.0,
    position_offset_z=10.0,
)


#: Errors of the backward (3B) truth: other biases and drifts on the same orbit.
TRUTH_ERRORS_BACKWARD = dict(
    roll_bias=-2e-5,
    pitch_bias=3e-5,
    yaw_bias=-6e-5,
    roll_drift=-1e-6,
    pitch_drift=2e-6,
    yaw_drift=-3e-6,
    position_offset_x=20.0,
    position_offset_y=-15.0,
    position_offset_z=10.0,
)


def aster_size_pair(lon0: float, lat0: float, h0: float):
    """``(nadir, backward)``: the simulator's full-size ASTER pair geometry (3N 4100 x 4200,
    3B 5000 x 4600 pixels, :func:`aster_geometry_parameters`) looking at ``(lon0, lat0, h0)``
    (degrees, metres above the ellipsoid), without errors."""
    p = aster_geometry_parameters()
    b = p["bands"]
    return pushbroom_pair(
        lon0,
        lat0,
        h0,
        (4100, 4200),
        (b["3N"]["along_deg"], b["3B"]["along_deg"]),
        gsd=p["gsd_m"],
        altitude=p["altitude_m"],
        line_period=p["line_period_s"],
        cross_track_tilt_deg=-p["cross_track_right_deg"],
        right_size=(5000, 4600),
    )


@functools.lru_cache(maxsize=1)
def aster_pair_scene():
    """``(metadata_3N, metadata_3B, truth_3N, truth_3B, dem)``: the simulator's full-size ASTER
    pair geometry (:func:`aster_size_pair`) over the bundled DEM, the truths carrying
    :data:`TRUTH_ERRORS` and :data:`TRUTH_ERRORS_BACKWARD`."""
    dem = DEM.bundled()
    w, s, e, n = dem.bounds_lonlat()
    lon0, lat0 = (w + e) / 2, (s + n) / 2
    nadir, back = aster_size_pair(lon0, lat0, float(dem.sample(lon0, lat0)))
    return (
        nadir,
        back,
        nadir.with_parameters(**TRUTH_ERRORS),
        back.with_parameters(**TRUTH_ERRORS_BACKWARD),
        dem,
    )


def aster_nadir_scene():
    """``(metadata, truth, dem)``: the 3N image of :func:`aster_pair_scene` (real granule
    pointing, IFOV, orbit height and line period) and its truth with :data:`TRUTH_ERRORS`."""
    nadir, _, truth, _, dem = aster_pair_scene()
    return nadir, truth, dem


def points_at_pixels(truth, dem, col, row, *, noise_px: float = 0.3, seed: int = 0):
    """Ground points on ``dem`` seen by ``truth`` at pixels ``(col, row)``; returns a dict of
    arrays ``lon, lat, h`` (deg, deg, ellipsoidal m), ``col, row`` (noisy by ``noise_px``) and
    ``col_true, row_true``, for the pixels whose DEM localisation converged."""
    rng = np.random.default_rng(seed)
    col, row = np.asarray(col, float), np.asarray(row, float)
    loc = truth.localize_dem(col, row, dem, threshold=0.001)
    ok = loc.converged
    if not ok.any():
        raise InputError("no simulated point falls on the DEM")
    n = int(ok.sum())
    return dict(
        lon=loc.lon[ok],
        lat=loc.lat[ok],
        h=loc.h[ok],
        col_true=col[ok],
        row_true=row[ok],
        col=col[ok] + rng.normal(0, noise_px, n),
        row=row[ok] + rng.normal(0, noise_px, n),
    )


def random_pixels(model, n: int, *, seed: int = 0, margin: float = 20.0):
    """``n`` uniform random pixels at least ``margin`` pixels inside the image."""
    rng = np.random.default_rng(seed)
    return (
        rng.uniform(margin, model.width - 1 - margin, n),
        rng.uniform(margin, model.height - 1 - margin, n),
    )


def to_control_points(pts: dict, role):
    """A :class:`~stereodem.sensor.io.gcps.ControlPoints` of a :func:`points_at_pixels` dict."""
    n = pts["lon"].size
    return ControlPoints.from_arrays(
        pts["lon"],
        pts["lat"],
        pts["h"],
        pts["col"],
        pts["row"],
        role=np.broadcast_to(np.asarray(role), (n,)).astype(str),
    )
