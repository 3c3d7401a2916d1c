"""Simulated control points for sensor-model adjustment experiments.

A metadata model (what the product header says) and a "truth" model (the same sensor with
ephemeris and attitude biases and drifts) of the simulator's ASTER 3N geometry; ground points
on the bundled DEM seen by the truth at chosen pixels, with Gaussian measurement noise on the
image coordinates. Used by the orbital-model tests and ``benchmarks/bench_topan_sets.py``.
"""
from __future__ import annotations

import functools

import numpy as np

from stereodem.sensor.errors import InputError

#: Pointing and position errors of the truth against the metadata (PushbroomModel parameters):
#: about 1.5 px of attitude bias, 0.5 px of attitude drift over the scene, 20 m of position.
TRUTH_ERRORS = dict(roll_bias=3e-5, pitch_bias=-2e-5, yaw_bias=1e-4, roll_drift=2e-6,
                    pitch_drift=-1.5e-6, yaw_drift=5e-6, position_offset_x=20.0,
                    position_offset_y=-15.0, position_offset_z=10.0)


@functools.lru_cache(maxsize=2)
def aster_nadir_scene(width: int = 4100, height: int = 4200):
    """``(metadata, truth, dem)``: the simulator's ASTER 3N geometry (real granule pointing,
    IFOV, orbit height and line period) over the bundled DEM, and the same camera with
    :data:`TRUTH_ERRORS`."""
    from stereodem.sensor.geo.dem import DEM
    from stereodem.sensor.simulation.simulate import aster_geometry_parameters, pushbroom_pair
    p = aster_geometry_parameters()
    b = p["bands"]
    dem = DEM.bundled()
    w, s, e, n = dem.bounds_lonlat()
    lon0, lat0 = (w + e) / 2, (s + n) / 2
    h0 = float(dem.sample(lon0, lat0))
    nadir, _ = pushbroom_pair(lon0, lat0, h0, (width, height), (b["3N"]["along_deg"], b["3B"]["along_deg"]),
                              gsd=p["gsd_m"], altitude=p["altitude_m"], line_period=p["line_period_s"],
                              cross_track_tilt_deg=-p["cross_track_right_deg"])
    return nadir, nadir.with_parameters(**TRUTH_ERRORS), dem


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
    return dict(lon=loc.lon[ok], lat=loc.lat[ok], h=loc.h[ok], col_true=col[ok], row_true=row[ok],
                col=col[ok] + rng.normal(0, noise_px, n), row=row[ok] + rng.normal(0, noise_px, n))


def random_pixels(model, n: int, *, seed: int = 0, margin: float = 20.0):
    """``n`` uniform random pixels at least ``margin`` pixels inside the image."""
    rng = np.random.default_rng(seed)
    return (rng.uniform(margin, model.width - 1 - margin, n),
            rng.uniform(margin, model.height - 1 - margin, n))


def to_control_points(pts: dict, role):
    """A :class:`~stereodem.sensor.io.gcps.ControlPoints` of a :func:`points_at_pixels` dict."""
    from stereodem.sensor.io.gcps import ControlPoints
    n = pts["lon"].size
    return ControlPoints.from_arrays(pts["lon"], pts["lat"], pts["h"], pts["col"], pts["row"],
                                     role=np.broadcast_to(np.asarray(role), (n,)).astype(str))
