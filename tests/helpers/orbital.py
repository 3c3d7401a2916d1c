"""Shared pieces of the orbital-model tests: a simulated ASTER 3N geometry whose ephemeris and
attitude carry biases and drifts, GCP/ICP sets from it, and a small Gauss-Newton used only by
the tests (the package's estimation engine lives in stereodem.sensor.estimation)."""

from __future__ import annotations

import numpy as np

from stereodem.sensor.models.parameters import project_jacobian
from stereodem.sensor.simulation.control_points import (
    aster_nadir_scene,
    points_at_pixels,
    random_pixels,
)

RIGOROUS_SET = ["roll_bias", "pitch_bias", "yaw_bias", "roll_drift", "pitch_drift", "yaw_drift"]
NOISE_PX = 0.3


def aster_scene():
    """``(metadata_model, truth_model, dem)`` (:func:`aster_nadir_scene`)."""
    return aster_nadir_scene()


def control_points(n_gcp, n_icp=40, seed=3):
    """Ground points on the DEM seen by the truth at random pixels; returns dicts ``gcp`` and
    ``icp`` with lon, lat, h, col, row (noisy, 0.3 px) and col_true, row_true."""
    _, truth, dem = aster_scene()
    pts = points_at_pixels(
        truth,
        dem,
        *random_pixels(truth, 3 * (n_gcp + n_icp), seed=seed),
        noise_px=NOISE_PX,
        seed=seed,
    )
    out = {}
    for key, sl in (("gcp", slice(0, n_gcp)), ("icp", slice(n_gcp, n_gcp + n_icp))):
        out[key] = {k: v[sl] for k, v in pts.items()}
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
