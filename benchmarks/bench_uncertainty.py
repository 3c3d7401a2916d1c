"""Benchmark: issue #17 — Bettemir's analyses reproduced with stereodem's propagation engine,
the thesis footprints, and the speed of the uncertainty maps.

1. **Bettemir (2010), Tables 3–11.** The paper's simulated BilSAT-like frame camera (f = 500 mm,
   pixel 0.0074 mm, 2048 × 2048, Table 1 interior values, attitude 7.5643° / −1.4771° /
   0.4629°) on a 686 km circular sun-synchronous orbit (i = 98.1°, descending over
   39.9° N 32.0° E), built as a :class:`stereodem.sensor.models.frame.FrameCamera` (the thesis's
   DRM chain), terrain at 1000 m. σ_N and σ_E (HU) at pixels (1,1), (1024,1024), (2048,2048)
   and the grouped shares POS / ATT / DEM / δt (+ the interior group the paper leaves out) come
   from :func:`stereodem.ortho.uncertainty.propagation.ground_jacobian` and ``J D Jᵀ``.
   **Inferred inputs** (not in the paper; extraction notes §5.3), three of them **calibrated on
   the same tables** (so the agreement of the 54 cells is a calibration, not a prediction):
   σ_pitch = σ_yaw = 0.306 × STC
   with σ_roll = STC; GPS value / 3 per ECEF axis; σ_k1 = 3.5·10⁻⁶ mm⁻² standing for the whole
   interior group; the orbit state; terrain height 1000 m; paper pixel rows counted upward.
   Stated: STC, GPS, σ_DEM = 5 m, σ_t ∈ {5/3, 1, 1/3} ms. Predicted independently of the
   calibration (orbit and camera geometry only): the imaging-time, roll and DEM levers at the
   centre pixel, compared with the levers the paper's tables imply (``independent_levers``).
   The VU columns need the paper's DEM patches (unpublished): the Hirvonen fit is run on
   synthetic 10 × 10 SRTM-spaced patches whose slopes are the paper-implied ones (inferred).
2. **Thesis Tables 8.6/8.7**: the nine footprint points from the Table B.8 parameters (heading ψ
   and a constant terrain height fitted), misfit in metres.
3. **Speed** (2 cores, shared with other jobs): first-order maps of a full ASTER-size scene
   orthoimage (3N, 4100 × 4200 px, 15 m grid) against the orthorectification itself, both in
   this process, alternately, three times (wall and CPU seconds, the median ratio, the load
   average); a 1000-sample Latin-hypercube Monte Carlo on a 64 × 64 evaluation grid.

Run: ``python benchmarks/bench_uncertainty.py [--skip-speed | --speed-only]``; writes
benchmarks/results/bench_uncertainty.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereodem.core import geodesy  # noqa: E402
from stereodem.core.jsonutil import dumps as strict_json  # noqa: E402
from stereodem.ortho.uncertainty.propagation import ground_jacobian, propagate, variance_shares  # noqa: E402
from stereodem.sensor.models.frame import FrameCamera  # noqa: E402

ARCSEC = np.pi / 180 / 3600

# --------------------------------------------------------------------------- the paper's tables
# analysis: (table, STC arcsec, GPS m, sigma_t ms)
ANALYSES = {
    1: (3, 150, 10, 5 / 3),
    2: (4, 30, 10, 5 / 3),
    3: (5, 15, 10, 5 / 3),
    4: (6, 6, 10, 5 / 3),
    5: (7, 6, 10, 1.0),
    6: (8, 3, 10, 1.0),
    7: (9, 3, 10, 1 / 3),
    8: (10, 1, 10, 1 / 3),
    9: (11, 1, 1, 1 / 3),
}
PIXELS = [(1, 1), (1024, 1024), (2048, 2048)]
# per analysis: component -> rows for the 3 pixels: (POS, ATT, DEM, dt, HU, VU sm, VU st)
PAPER = {
    1: {
        "N": [
            (0.0003, 0.9958, 0.0, 0.0037, 183.785, 2.347, 8.498),
            (0.0003, 0.9961, 0.0, 0.0037, 183.271, 2.340, 8.474),
            (0.0003, 0.9957, 0.0, 0.0037, 182.767, 2.334, 8.451),
        ],
        "E": [
            (4e-05, 0.9998, 1e-06, 3e-05, 499.023, 7.016, 15.006),
            (4e-05, 0.9999, 1e-06, 3e-05, 499.049, 7.016, 15.007),
            (4e-05, 0.9998, 1e-06, 3e-05, 498.904, 7.014, 15.003),
        ],
    },
    2: {
        "N": [
            (0.0060, 0.9041, 8e-05, 0.0829, 38.576, 0.493, 1.784),
            (0.0061, 0.9100, 8e-05, 0.0838, 38.349, 0.490, 1.773),
            (0.0061, 0.9031, 8e-05, 0.0837, 38.382, 0.490, 1.775),
        ],
        "E": [
            (0.0009, 0.9958, 3e-05, 0.0007, 100.006, 1.406, 3.007),
            (0.0009, 0.9983, 3e-05, 0.0007, 99.889, 1.404, 3.004),
            (0.0009, 0.9958, 3e-05, 0.0007, 99.983, 1.406, 3.007),
        ],
    },
    3: {
        "N": [
            (0.0188, 0.7021, 0.0002, 0.2574, 21.887, 0.279, 1.012),
            (0.0193, 0.7164, 0.0003, 0.2640, 21.610, 0.276, 0.999),
            (0.0189, 0.6997, 0.0002, 0.2594, 21.803, 0.278, 1.008),
        ],
        "E": [
            (0.0036, 0.9834, 0.0001, 0.0028, 50.317, 0.707, 1.513),
            (0.0036, 0.9934, 0.0001, 0.0029, 50.068, 0.704, 1.506),
            (0.0036, 0.9834, 0.0001, 0.0028, 50.307, 0.707, 1.513),
        ],
    },
    4: {
        "N": [
            (0.0458, 0.2738, 0.0006, 0.6274, 14.019, 0.179, 0.631),
            (0.0484, 0.2879, 0.0006, 0.6631, 13.636, 0.174, 0.613),
            (0.0459, 0.2715, 0.0006, 0.6291, 14.000, 0.179, 0.631),
        ],
        "E": [
            (0.0204, 0.9046, 0.0008, 0.0162, 20.985, 0.295, 0.648),
            (0.0217, 0.9603, 0.0008, 0.0172, 20.370, 0.286, 0.631),
            (0.0204, 0.9043, 0.0008, 0.0162, 20.984, 0.295, 0.647),
        ],
    },
    5: {
        "N": [
            (0.074, 0.441, 0.001, 0.400, 11.044, 0.141, 0.511),
            (0.081, 0.481, 0.001, 0.438, 10.554, 0.135, 0.488),
            (0.074, 0.438, 0.001, 0.401, 11.019, 0.141, 0.510),
        ],
        "E": [
            (0.021, 0.914, 0.001, 0.006, 20.876, 0.293, 0.628),
            (0.022, 0.971, 0.001, 0.006, 20.258, 0.285, 0.609),
            (0.021, 0.914, 0.001, 0.006, 20.874, 0.293, 0.628),
        ],
    },
    6: {
        "N": [
            (0.110, 0.165, 0.001, 0.597, 9.033, 0.115, 0.352),
            (0.126, 0.188, 0.002, 0.684, 8.440, 0.108, 0.318),
            (0.110, 0.163, 0.001, 0.598, 9.028, 0.115, 0.352),
        ],
        "E": [
            (0.066, 0.727, 0.002, 0.019, 11.705, 0.165, 0.418),
            (0.081, 0.893, 0.003, 0.023, 10.561, 0.148, 0.390),
            (0.066, 0.726, 0.002, 0.019, 11.709, 0.165, 0.417),
        ],
    },
    7: {
        "N": [
            (0.2381, 0.3559, 0.0031, 0.1305, 6.148, 0.079, 0.284),
            (0.3281, 0.4878, 0.0043, 0.1798, 5.238, 0.067, 0.242),
            (0.2387, 0.3528, 0.0031, 0.1308, 6.141, 0.078, 0.284),
        ],
        "E": [
            (0.0668, 0.7392, 0.0025, 0.0021, 11.607, 0.163, 0.349),
            (0.0824, 0.9119, 0.0031, 0.0026, 10.452, 0.147, 0.314),
            (0.0668, 0.7384, 0.0025, 0.0021, 11.611, 0.163, 0.349),
        ],
    },
    8: {
        "N": [
            (0.348, 0.058, 0.005, 0.191, 5.083, 0.065, 0.204),
            (0.579, 0.096, 0.008, 0.317, 3.942, 0.050, 0.137),
            (0.348, 0.057, 0.005, 0.191, 5.088, 0.065, 0.205),
        ],
        "E": [
            (0.195, 0.240, 0.007, 0.006, 6.797, 0.096, 0.235),
            (0.435, 0.535, 0.016, 0.014, 4.549, 0.064, 0.182),
            (0.194, 0.239, 0.007, 0.006, 6.807, 0.096, 0.235),
        ],
    },
    9: {
        "N": [
            (0.005, 0.088, 0.007, 0.291, 4.115, 0.053, 0.184),
            (0.014, 0.224, 0.018, 0.744, 2.574, 0.033, 0.103),
            (0.005, 0.087, 0.007, 0.291, 4.120, 0.053, 0.184),
        ],
        "E": [
            (0.002, 0.297, 0.009, 0.008, 6.106, 0.086, 0.190),
            (0.008, 0.939, 0.029, 0.024, 3.433, 0.048, 0.119),
            (0.002, 0.296, 0.009, 0.008, 6.118, 0.086, 0.190),
        ],
    },
}
GROUPS = {
    "POS": ["x", "y", "z"],
    "ATT": ["roll", "pitch", "yaw"],
    "DEM": ["dem_height"],
    "dt": ["imaging_time"],
    "INT": ["dx_mm", "dy_mm", "k1", "k2", "p1", "p2"],
}
NAMES = [n for g in GROUPS.values() for n in g]
# paper-implied slopes (VU/HU, extraction §5.2) — inferred, the patches are unpublished
SLOPES = {"smooth": (0.01406, 0.01277), "steep": (0.03007, 0.04624)}  # (dh/dE, dh/dN)
TERRAIN_H = 1000.0


def orbit_state(lat0=39.9, lon0=32.0, altitude=686e3, inclination=98.1):
    """ECEF position and Earth-fixed velocity of a circular orbit passing over (lon0, lat0),
    descending (heading from the inclination, inertial)."""
    r0 = np.array(geodesy.geodetic_to_ecef(lon0, lat0, altitude))
    enu = geodesy.enu_basis(lon0, lat0)
    az = np.pi - np.arcsin(np.cos(np.radians(inclination)) / np.cos(np.radians(lat0)))  # descending
    t_dir = np.sin(az) * enu[0] + np.cos(az) * enu[1]
    v_in = np.sqrt(geodesy.GM / np.linalg.norm(r0)) * t_dir
    return r0, v_in - np.cross([0.0, 0.0, geodesy.OMEGA_EARTH], r0)


def bettemir_camera():
    r, v = orbit_state()
    return FrameCamera(
        width=2048,
        height=2048,
        focal_mm=500.0,
        pitch_mm=0.0074,
        position=r,
        velocity=v,
        roll=np.radians(7.5643),
        pitch=np.radians(-1.4771),
        yaw=np.radians(0.4629),
        dx_mm=0.01,
        dy_mm=0.01,
        k1=1e-5,
        k2=1e-16,
        p1=1e-10,
        p2=1e-10,
    )


def covariance(stc, gps, sigma_t_ms, *, pitch_yaw_factor=0.306, gps_divisor=3.0, sigma_k1=3.5e-6):
    s = dict(
        x=gps / gps_divisor,
        y=gps / gps_divisor,
        z=gps / gps_divisor,
        roll=stc * ARCSEC,
        pitch=pitch_yaw_factor * stc * ARCSEC,
        yaw=pitch_yaw_factor * stc * ARCSEC,
        dem_height=5.0,
        imaging_time=sigma_t_ms * 1e-3,
        k1=sigma_k1,
    )
    return np.diag([s.get(n, 0.0) ** 2 for n in NAMES])


def hirvonen_patch_slopes(gE, gN, *, dx=71.0, dy=92.6, c=12.2, seed=0):
    """Slopes recovered by the Hirvonen-weighted quadratic fit (the project's kernels) from a
    synthetic 11 × 11 SRTM-spaced patch with gradient (gE, gN), curvature and 1 m noise."""
    from stereodem.ortho.uncertainty.maps import hirvonen_slope_kernels

    rng = np.random.default_rng(seed)
    k = np.arange(11) - 5
    E, N = np.meshgrid(k * dx, -k * dy)
    z = (
        1000
        + gE * E
        + gN * N
        + 2e-5 * E * E
        - 1e-5 * N * N
        + 1.5e-5 * E * N
        + rng.normal(0, 1.0, E.shape)
    )
    kE, kN = hirvonen_slope_kernels(11, (dx, dy), c)
    return float((kE * z).sum()), float((kN * z).sum())


def bettemir(sigma_t_medium=1.0):
    cam = bettemir_camera()
    crs = geodesy.utm_crs(32.0, 39.9)
    col = np.array([x - 0.5 for x, _ in PIXELS])
    row = np.array([2048.5 - y for _, y in PIXELS])  # rows counted upward (inferred)
    lon, lat = cam.localize(col, row, np.full(3, TERRAIN_H))
    gj = ground_jacobian(cam, lon, lat, np.full(3, TERRAIN_H), NAMES, crs)
    slopes = {k: hirvonen_patch_slopes(*v) for k, v in SLOPES.items()}
    rows, hu_diffs = [], []
    for a, (table, stc, gps, st) in ANALYSES.items():
        if st == 1.0:
            st = sigma_t_medium
        D = covariance(stc, gps, st)
        C = propagate(gj.J, D)
        sh = variance_shares(gj.J, D, GROUPS, NAMES)
        for comp, ci in (("N", 1), ("E", 0)):
            for p in range(3):
                hu = float(np.sqrt(C[p, ci, ci]))
                ref = PAPER[a][comp][p]
                g = (
                    slopes["smooth"][0 if comp == "E" else 1],
                    slopes["steep"][0 if comp == "E" else 1],
                )
                cell = {
                    "analysis": a,
                    "table": table,
                    "component": comp,
                    "pixel": PIXELS[p],
                    "HU": round(hu, 3),
                    "HU_paper": ref[4],
                    "HU_rel_diff_pct": round(100 * (hu / ref[4] - 1), 2),
                    "shares": {k: round(float(sh[k][p, ci]), 4) for k in GROUPS},
                    "shares_paper": dict(zip(["POS", "ATT", "DEM", "dt"], ref[:4])),
                    "VU_smooth": round(abs(g[0]) * hu, 3),
                    "VU_smooth_paper": ref[5],
                    "VU_steep": round(abs(g[1]) * hu, 3),
                    "VU_steep_paper": ref[6],
                }
                rows.append(cell)
                hu_diffs.append(cell["HU_rel_diff_pct"])
    d = np.abs(hu_diffs)
    worst = sorted(rows, key=lambda r: -abs(r["HU_rel_diff_pct"]))[:5]
    centre = gj.J[1]
    return {
        "cells": rows,
        "median_abs_HU_diff_pct": float(np.median(d)),
        "max_abs_HU_diff_pct": float(d.max()),
        "mean_abs_HU_diff_pct": float(d.mean()),
        "largest": [
            {
                k: r[k]
                for k in (
                    "analysis",
                    "table",
                    "component",
                    "pixel",
                    "HU",
                    "HU_paper",
                    "HU_rel_diff_pct",
                )
            }
            for r in worst
        ],
        "levers_centre": {
            "dN_dt_m_per_s": float(centre[1, NAMES.index("imaging_time")]),
            "dE_dt_m_per_s": float(centre[0, NAMES.index("imaging_time")]),
            "dE_droll_m_per_arcsec": float(centre[0, NAMES.index("roll")] * ARCSEC),
            "dN_dh": float(centre[1, NAMES.index("dem_height")]),
            "dE_dh": float(centre[0, NAMES.index("dem_height")]),
        },
        "hirvonen_slopes_recovered": {
            k: {"dh_dE": v[0], "dh_dN": v[1], "set_dh_dE": SLOPES[k][0], "set_dh_dN": SLOPES[k][1]}
            for k, v in slopes.items()
        },
    }


#: levers implied by the paper's tables themselves (table-internal back-out: each source's
#: sigma divided by its input sigma is constant across the analyses; notes
#: ../shared/notes/seed-bettemir-paper.md section 5.2), centre pixel; signs are not published
PAPER_LEVERS = {
    "dN_dt_m_per_s": 6663.0,
    "dE_dt_m_per_s": 1600.0,
    "dE_droll_m_per_arcsec": 3.3268,
    "dN_dh": 0.069,
    "dE_dh": 0.116,
}
#: the inputs fixed by matching the same tables (so the 54-cell agreement is a calibration)
CALIBRATED = [
    "sigma_pitch = sigma_yaw = 0.306 x STC (sigma_roll = STC)",
    "GPS value / 3 per ECEF axis",
    "sigma_k1 = 3.5e-6 mm^-2 standing for the interior group",
]


def independent_levers(levers: dict) -> dict:
    """The model's centre-pixel levers (orbit geometry and camera only: no calibrated input
    enters them) against the paper-implied ones, relative difference of the magnitudes in %."""
    return {
        k: {
            "model": float(levers[k]),
            "paper_implied": v,
            "abs_rel_diff_pct": round(100 * abs(abs(levers[k]) / v - 1), 2),
        }
        for k, v in PAPER_LEVERS.items()
    }


def headline(res):
    """Horizontal totals and the eq 13 vertical of analyses 1, 2, 4 (steep patch)."""
    out = {}
    for a in (1, 2, 4):
        cells = [c for c in res["cells"] if c["analysis"] == a]
        get = lambda comp, p, k: next(
            c[k]
            for c in cells  # noqa: B023
            if c["component"] == comp and c["pixel"] == PIXELS[p]
        )
        out[a] = {
            "horizontal_centre_m": float(np.hypot(get("N", 1, "HU"), get("E", 1, "HU"))),
            "horizontal_corner_m": float(np.hypot(get("N", 0, "HU"), get("E", 0, "HU"))),
            "vertical_eq13_steep_m": float(
                np.sqrt(25 + get("N", 0, "VU_steep") ** 2 + get("E", 0, "VU_steep") ** 2)
            ),
        }
    out["paper_claims"] = {
        "1": "VU up to 15 m, total vertical up to 17 m",
        "2": "vertical only 1 m above sigma_DEM (6 m)",
        "4": "24 m horizontal, 5.5 m vertical (5.5 not derivable: eq 13 gives ~5.08)",
    }
    return out


# --------------------------------------------------------------------------- thesis footprints
B8 = dict(
    position=(4496191.626, 3024516.853, 4532983.158),
    roll=0.14746,
    pitch=-0.03813,
    yaw=0.11231,
    focal_mm=175.92984,
    dx_mm=0.63002,
    dy_mm=-0.83923,
    k1=0.00036,
    k2=-4.44e-6,
    p1=-0.00051,
    p2=0.00058,
)
T86 = np.array(
    [[40.0315, 39.7544, 39.4745], [40.0548, 39.7899, 39.5175], [40.0948, 39.8213, 39.5465]]
)
T87 = np.array(
    [[32.3217, 32.3767, 32.4080], [32.6910, 32.7290, 32.7704], [33.0501, 33.0825, 33.1311]]
)


def thesis_camera(heading_deg):
    r = np.array(B8["position"], float)
    lon, lat, _ = geodesy.ecef_to_geodetic(*r)
    enu = geodesy.enu_basis(float(lon), float(lat))
    t = np.sin(np.radians(heading_deg)) * enu[0] + np.cos(np.radians(heading_deg)) * enu[1]
    v_in = np.sqrt(geodesy.GM / np.linalg.norm(r)) * t
    v = v_in - np.cross([0.0, 0.0, geodesy.OMEGA_EARTH], r)
    return FrameCamera(
        width=2048, height=2048, pitch_mm=0.0074, velocity=v, **{k: v_ for k, v_ in B8.items()}
    )


def thesis_footprints():
    xs = np.array([1.0, 1024.0, 2048.0])
    X, Y = np.meshgrid(xs, xs, indexing="ij")  # rows = x, columns = y
    col, row = (X - 0.5).ravel(), (Y - 0.5).ravel()

    def misfit(psi, h):
        lon, lat = thesis_camera(psi).localize(col, row, np.full(9, h))
        dN = (lat - T86.ravel()) * 111_000.0
        dE = (lon - T87.ravel()) * 111_000.0 * np.cos(np.radians(39.8))
        return float(np.sqrt(np.mean(dN**2 + dE**2))), lon, lat

    psis = np.arange(340.0, 356.0, 0.1)
    best0 = min(psis, key=lambda p: misfit(p, 0.0)[0])
    hs = np.arange(0.0, 2500.0, 20.0)
    grid = [(misfit(p, h)[0], p, h) for p in np.arange(best0 - 2, best0 + 2, 0.1) for h in hs]
    m1, p1, h1 = min(grid)
    return {
        "heading_fit_deg_h0": float(best0),
        "rms_misfit_m_h0": misfit(best0, 0.0)[0],
        "heading_fit_deg": float(p1),
        "terrain_height_fit_m": float(h1),
        "rms_misfit_m": m1,
        "notes_expectation": "198 m RMS at h = 0 (psi 347.7), 87 m with h ~ 1.38 km",
        "note": (
            "nominal localisations (the Monte Carlo mean to first order); input sigmas unpublished"
        ),
    }


# --------------------------------------------------------------------------- speed

REPEATS = 3
#: the previous measurement (per-cell image-side terms at full resolution), for reference
BEFORE = {
    "orthorectify_s": 4.18,
    "first_order_maps_s": 58.41,
    "ratio_maps_over_ortho": 13.982,
    "lattice_step_cells": 64,
    "interpolation_error_relative": 3.735e-06,
    "commit": "a6e4845",
}


def speed():
    from stereodem.ortho.drm import orthorectify
    from stereodem.ortho.grid import grid_for_model
    from stereodem.ortho.uncertainty.maps import ortho_uncertainty_maps
    from stereodem.ortho.uncertainty.sampling import (
        field_displacements,
        ground_displacements,
        lhs_normal,
    )
    from stereodem.sensor.simulation.control_points import aster_size_pair

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_aster_scene import mirrored_dem

    dem = mirrored_dem().to_reference("ellipsoid")
    lon0, lat0 = (lambda b: ((b[0] + b[2]) / 2, (b[1] + b[3]) / 2))(dem.bounds_lonlat())
    left, _ = aster_size_pair(lon0, lat0, float(dem.sample(lon0, lat0)))
    grid = grid_for_model(left, dem, res=15.0)
    img = (np.random.default_rng(0).random((4200, 4100)) * 255).astype(np.uint8)
    threads = os.cpu_count() or 1
    names = [
        "roll_bias",
        "pitch_bias",
        "yaw_bias",
        "time_offset",
        "position_offset_x",
        "position_offset_y",
        "position_offset_z",
        "look_scale",
        "dem_height",
    ]
    sig = np.array([2e-5, 2e-5, 2e-5, 1e-3, 5.0, 5.0, 5.0, 1e-5, 5.0])
    # the orthorectification and the first-order maps, alternately, REPEATS times in this process;
    # wall and CPU seconds (all threads) of each; the ratio of each pair, reported as the median
    load_before = os.getloadavg()
    runs = []
    for _ in range(REPEATS):
        w, c = time.perf_counter(), time.process_time()
        orthorectify(img, left, dem, grid=grid, threads=threads)
        t_ortho, c_ortho = time.perf_counter() - w, time.process_time() - c
        w, c = time.perf_counter(), time.process_time()
        um = ortho_uncertainty_maps(left, dem, grid, np.diag(sig**2), names, threads=threads)
        t_unc, c_unc = time.perf_counter() - w, time.process_time() - c
        runs.append(
            {
                "orthorectify_s": round(t_ortho, 2),
                "first_order_maps_s": round(t_unc, 2),
                "orthorectify_cpu_s": round(c_ortho, 2),
                "first_order_maps_cpu_s": round(c_unc, 2),
                "ratio": round(t_unc / t_ortho, 3),
                "ratio_cpu": round(c_unc / c_ortho, 3),
                "maps_parts_s": um.details.get("seconds"),
            }
        )
        print("speed run:", json.dumps(runs[-1]))
    load_after = os.getloadavg()
    med = lambda k: float(np.median([r[k] for r in runs]))
    # Monte Carlo: 1000 LHS samples on a 64 x 64 evaluation grid
    uu = np.linspace(0, grid.width - 1, 64)
    U, V = np.meshgrid(uu, np.linspace(0, grid.height - 1, 64))
    lon, lat = grid.lonlat(U.ravel(), V.ravel())
    h = dem.sample(lon, lat)
    ok = np.isfinite(h)
    lon, lat, h = lon[ok], lat[ok], h[ok]
    X = lhs_normal(np.diag(sig**2), 1000, seed=0)
    t = time.perf_counter()
    dE, dN, field_err = field_displacements(left, lon, lat, h, names, X, grid.crs, dem=dem)
    t_mc = time.perf_counter() - t
    sh_mc = np.hypot(dE.std(0, ddof=1), dN.std(0, ddof=1))
    from stereodem.ortho.uncertainty.propagation import first_order

    pu = first_order(left, lon, lat, h, names, np.diag(sig**2), grid.crs, dem=dem)
    # the field path against exact per-sample re-localisation (Newton) at a subset, 100 samples:
    # with the DEM (terrain curvature over the displacement is the difference) and without
    idx = np.arange(0, lon.size, 97)
    cmp = {}
    for label, d in (("on_dem", dem), ("flat", None)):
        e1, n1 = ground_displacements(
            left, lon[idx], lat[idx], h[idx], names, X[:100], grid.crs, dem=d
        )
        e2, n2, _ = field_displacements(
            left, lon[idx], lat[idx], h[idx], names, X[:100], grid.crs, dem=d
        )
        s1, s2 = (
            np.hypot(e1.std(0, ddof=1), n1.std(0, ddof=1)),
            np.hypot(e2.std(0, ddof=1), n2.std(0, ddof=1)),
        )
        cmp[label] = {
            "points": int(idx.size),
            "samples": 100,
            "max_sample_displacement_diff_m": float(
                max(np.abs(e1 - e2).max(), np.abs(n1 - n2).max())
            ),
            "max_sigma_rel_diff": float(np.max(np.abs(s2 / s1 - 1))),
        }
    return {
        "aster_scene": {
            "image_px": [4100, 4200],
            "grid": [grid.width, grid.height],
            "res_m": 15.0,
            "orthorectify_s": med("orthorectify_s"),
            "first_order_maps_s": med("first_order_maps_s"),
            "orthorectify_cpu_s": med("orthorectify_cpu_s"),
            "first_order_maps_cpu_s": med("first_order_maps_cpu_s"),
            "ratio_maps_over_ortho": med("ratio"),
            "ratio_cpu_maps_over_ortho": med("ratio_cpu"),
            "target_ratio": 2.0,
            "runs": runs,
            "contention": {
                "load_average_1_5_15_before": [round(v, 2) for v in load_before],
                "load_average_1_5_15_after": [round(v, 2) for v in load_after],
                "cores": os.cpu_count(),
                "note": "wall times vary with the load (other jobs on "
                "the cores), the ratio of each alternating pair less so",
            },
            "lattice_step_cells": um.step,
            "interpolation_error_relative": um.interpolation_error,
            "interpolation_error_measure": "max over check cells (lattice mid-cells and random "
            "cells) of the relative error of sigma_E, sigma_N, sigma_horizontal of the finished "
            "float32 maps against exact per-cell first-order propagation",
            "n_check_cells": um.details.get("n_check_cells"),
            "dem_position_error_px": um.details.get("dem_position_error_px"),
            "sigma_horizontal_median_m": float(np.nanmedian(um.sigma_horizontal)),
            "shares": um.shares,
            "threads": threads,
            "method": "terrain-free fields (image position, flat-terrain ground covariance, "
            "relief displacement, per-source covariances) exact on a lattice at two "
            "heights, interpolated in (x, y, h); per cell the DEM height and slope "
            "(Sherman-Morrison terrain factor), float32, blocks on threads",
            "before": BEFORE,
        },
        "monte_carlo_64x64_1000": {
            "seconds": round(t_mc, 2),
            "target_s": 30.0,
            "points": int(lon.size),
            "samples": 1000,
            "method": "image-shift field (exact perturbed model at "
            "9x9x3 nodes, Chebyshev fit, measured error) + local ground map",
            "field_error_px": field_err,
            "sigma_horizontal_median_m": float(np.median(sh_mc)),
            "max_rel_diff_vs_first_order": float(np.max(np.abs(sh_mc / pu.sigma_horizontal - 1))),
            "vs_exact_relocalisation": cmp,
        },
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument(
        "--speed-only",
        action="store_true",
        help="run only the speed part and update its entry of the existing results file",
    )
    args = ap.parse_args(argv)
    out = ROOT / "benchmarks" / "results" / "bench_uncertainty.json"
    dump = lambda r: strict_json(r, indent=1)  # noqa: E731
    if args.speed_only:
        res = json.loads(out.read_text()) if out.exists() else {}
        res["speed"] = speed()
        res.setdefault("machine", {})["note"] = (
            f"{os.cpu_count()} cores, load average "
            f"{os.getloadavg()[0]:.2f} when the speed part ended"
        )
        print("speed:", json.dumps(res["speed"]))
        out.write_text(dump(res))
        print(f"wrote {out}")
        return
    res = {
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "note": "2 cores shared with up to 7 agents: timings under contention",
        }
    }
    b = bettemir()
    b_adj = bettemir(sigma_t_medium=1.048)
    res["bettemir"] = b
    res["bettemir"]["with_medium_sigma_t_1.048ms"] = {
        "median_abs_HU_diff_pct": b_adj["median_abs_HU_diff_pct"],
        "max_abs_HU_diff_pct": b_adj["max_abs_HU_diff_pct"],
    }
    res["bettemir"]["inferred_inputs"] = [
        "sigma_pitch = sigma_yaw = 0.306 x STC, sigma_roll = STC",
        "GPS value / 3 per ECEF axis",
        "sigma_k1 = 3.5e-6 mm^-2 for the whole interior group (others 0)",
        "orbit: circular 686 km, i = 98.1 deg, descending over 39.9N 32.0E",
        "terrain height 1000 m",
        "paper pixel rows counted upward",
        "VU: synthetic patches with the paper-implied slopes",
    ]
    res["bettemir"]["headline"] = headline(b)
    res["bettemir"]["calibrated_inputs"] = CALIBRATED
    res["bettemir"]["independent_levers"] = independent_levers(b["levers_centre"])
    print(
        f"Bettemir 54 HU cells: median |diff| {b['median_abs_HU_diff_pct']:.2f} %, max "
        f"{b['max_abs_HU_diff_pct']:.2f} % (sigma_t medium 1.048 ms: median "
        f"{b_adj['median_abs_HU_diff_pct']:.2f} %, max {b_adj['max_abs_HU_diff_pct']:.2f} %)"
    )
    print(
        f"{'an':>2} {'T':>2} c  pixel        HU     paper   diff%   POS    ATT    DEM    dt     INT"
    )
    for c in b["cells"]:
        s = c["shares"]
        print(
            f"{c['analysis']:>2} {c['table']:>2} {c['component']} {str(c['pixel']):12s} "
            f"{c['HU']:8.3f} {c['HU_paper']:8.3f} {c['HU_rel_diff_pct']:+6.2f}  {s['POS']:.4f} "
            f"{s['ATT']:.4f} {s['DEM']:.4f} {s['dt']:.4f} {s['INT']:.4f}"
        )
    print("largest:", json.dumps(b["largest"]))
    print("levers:", json.dumps(b["levers_centre"]))
    res["thesis_footprints"] = thesis_footprints()
    print("thesis footprints:", json.dumps(res["thesis_footprints"]))
    if not args.skip_speed:
        res["speed"] = speed()
        print("speed:", json.dumps(res["speed"]))
    out.write_text(dump(res))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
