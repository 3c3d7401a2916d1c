"""Shared pieces of the orbital-model tests: a simulated ASTER 3N geometry whose ephemeris and
attitude carry biases and drifts, GCP/ICP sets from it, and a small Gauss-Newton used only by
the tests (the package's estimation engine lives in stereodem.sensor.estimation)."""
from __future__ import annotations

import functools

import numpy as np

from stereodem.sensor.geo.dem import DEM
from stereodem.sensor.models.parameters import project_jacobian
from stereodem.sensor.simulation.simulate import aster_geometry_parameters, pushbroom_pair

#: Pointing and position errors of the "truth" against the metadata (PushbroomModel parameters).
TRUTH_ERRORS = dict(roll_bias=3e-5, pitch_bias=-2e-5, yaw_bias=1e-4, roll_drift=2e-6,
                    pitch_drift=-1.5e-6, yaw_drift=5e-6, position_offset_x=20.0,
                    position_offset_y=-15.0, position_offset_z=10.0)
RIGOROUS_SET = ["roll_bias", "pitch_bias", "yaw_bias", "roll_drift", "pitch_drift", "yaw_drift"]
NOISE_PX = 0.3


@functools.lru_cache(maxsize=1)
def aster_scene():
    """``(metadata_model, truth_model, dem)``: the simulator's ASTER 3N geometry (full size)
    over the bundled DEM; the truth carries :data:`TRUTH_ERRORS`."""
    p = aster_geometry_parameters()
    b = p["bands"]
    dem = DEM.bundled()
    w, s, e, n = dem.bounds_lonlat()
    lon0, lat0 = (w + e) / 2, (s + n) / 2
    h0 = float(dem.sample(lon0, lat0))
    nadir, _ = pushbroom_pair(lon0, lat0, h0, (4100, 4200), (b["3N"]["along_deg"], b["3B"]["along_deg"]),
                              gsd=p["gsd_m"], altitude=p["altitude_m"], line_period=p["line_period_s"],
                              cross_track_tilt_deg=-p["cross_track_right_deg"], right_size=(5000, 4600))
    return nadir, nadir.with_parameters(**TRUTH_ERRORS), dem


def control_points(n_gcp, n_icp=40, seed=3):
    """Ground points on the DEM seen by the truth at random pixels; returns dicts ``gcp`` and
    ``icp`` with lon, lat, h, col, row (noisy, 0.3 px) and col_true, row_true."""
    _, truth, dem = aster_scene()
    rng = np.random.default_rng(seed)
    m = 3 * (n_gcp + n_icp)
    c = rng.uniform(20, truth.width - 21, m)
    r = rng.uniform(20, truth.height - 21, m)
    loc = truth.localize_dem(c, r, dem, threshold=0.001)
    ok = np.flatnonzero(loc.converged)[: n_gcp + n_icp]
    out = {}
    for key, idx in (("gcp", ok[:n_gcp]), ("icp", ok[n_gcp:])):
        out[key] = dict(lon=loc.lon[idx], lat=loc.lat[idx], h=loc.h[idx], col_true=c[idx], row_true=r[idx],
                        col=c[idx] + rng.normal(0, NOISE_PX, idx.size),
                        row=r[idx] + rng.normal(0, NOISE_PX, idx.size))
    return out


def gauss_newton(model, pts, names, iterations=12):
    """Least-squares fit of ``names`` to the points (unit weights); returns
    ``(model, condition number of the column-scaled design matrix, GCP RMSE px)``."""
    cond = np.inf
    for _ in range(iterations):
        pc, pr, J = project_jacobian(model, pts["lon"], pts["lat"], pts["h"], names)
        res = np.concatenate([pts["col"] - pc, pts["row"] - pr])
        A = np.concatenate([J[:, 0, :], J[:, 1, :]])
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        As = A / scale
        sv = np.linalg.svd(As, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        dx = np.linalg.lstsq(As, res, rcond=None)[0] / scale
        vals = model.parameters()
        model = model.with_parameters(**{n: vals[n] + d for n, d in zip(names, dx)})
        if np.max(np.abs(dx * scale)) < 1e-6:
            break
    pc, pr = model.project(pts["lon"], pts["lat"], pts["h"])
    return model, cond, rmse(pc - pts["col"], pr - pts["row"])


def rmse(dc, dr):
    """Radial RMSE (px) of column and row residuals."""
    return float(np.sqrt(np.mean(np.asarray(dc) ** 2 + np.asarray(dr) ** 2)))


def icp_rmse(model, icp, *, true=False):
    pc, pr = model.project(icp["lon"], icp["lat"], icp["h"])
    if true:
        return rmse(pc - icp["col_true"], pr - icp["row_true"])
    return rmse(pc - icp["col"], pr - icp["row"])
