"""Ok (2005) Table 6.15 structure on a simulated ASTER scene: every orthorectification model,
RMSE at GCPs and at independent check points (pixels) for several GCP counts.

The scene is the simulator's ``aster`` preset (real granule geometry, bundled SRTM). Points are
random left-image pixels localised exactly on the DEM; their image coordinates get 0.3 px of
Gaussian measurement noise (the thesis's GCPs were measured by hand). The "physical" row is the
exact pushbroom model with a pointing bias of (2, -1.5) px, corrected by the mean GCP
residual (bias compensation), i.e. a rigorous model adjusted with GCPs.

    python benchmarks/bench_ortho_models.py

Writes benchmarks/results/bench_ortho_models.json and .md.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from stereodem.sensor.models.generic import MODEL_NAMES, fit_model, minimum_gcps
from stereodem.sensor.simulation.simulate import simulate_scene

ROOT = Path(__file__).resolve().parents[1]
COUNTS = (10, 20, 40)
N_CHECK = 60
NOISE_PX = 0.3


def physical_rows(model, lon, lat, h, col, row, gi, ci, bias=(2.0, -1.5)):
    pc, pr = model.project(lon, lat, h)
    pc, pr = pc + bias[0], pr + bias[1]            # the uncorrected model's pointing error
    shift = np.array([np.mean(col[gi] - pc[gi]), np.mean(row[gi] - pr[gi])])
    rc, rr = pc + shift[0] - col, pr + shift[1] - row
    rm = lambda idx: float(np.sqrt(np.mean(rc[idx] ** 2 + rr[idx] ** 2)))   # noqa: E731
    return rm(gi), rm(ci)


def main():
    t0 = time.perf_counter()
    sc = simulate_scene("aster", size=(1200, 1200), seed=11, n_points=max(COUNTS) + N_CHECK + 20)
    rng = np.random.default_rng(5)
    pts = sc.points
    lon = np.array([p["lon"] for p in pts])
    lat = np.array([p["lat"] for p in pts])
    h = np.array([p["h"] for p in pts])
    col = np.array([p["col"] for p in pts]) + rng.normal(0, NOISE_PX, len(pts))
    row = np.array([p["row"] for p in pts]) + rng.normal(0, NOISE_PX, len(pts))
    ci = np.arange(len(pts) - N_CHECK, len(pts))
    table = {}
    for n in COUNTS:
        gi = np.arange(n)
        g = (lon[gi], lat[gi], h[gi], col[gi], row[gi])
        chk = (lon[ci], lat[ci], h[ci], col[ci], row[ci])
        table.setdefault("physical (bias-compensated)", {})[n] = dict(
            zip(("gcp", "check"), physical_rows(sc.left_model, lon, lat, h, col, row, gi, ci)))
        for name in MODEL_NAMES:
            if n < minimum_gcps(name):
                table.setdefault(name, {})[n] = None
                continue
            try:
                _, rep = fit_model(name, *g, check=chk)
                table.setdefault(name, {})[n] = dict(gcp=rep.gcp_rmse, check=rep.check_rmse,
                                                     cond=rep.condition_number)
            except Exception as exc:           # report, do not hide
                table.setdefault(name, {})[n] = dict(error=str(exc))
    lines = ["| model | " + " | ".join(f"{n} GCP: GCP / check" for n in COUNTS) + " |",
             "|---|" + "---|" * len(COUNTS)]
    for name, row_ in table.items():
        cells = []
        for n in COUNTS:
            v = row_.get(n)
            cells.append("-" if v is None else v.get("error", "")[:20] if "error" in v
                         else f"{v['gcp']:.2f} / {v['check']:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    md = "\n".join(lines)
    print(md)
    res = dict(scene="aster preset 1200x1200, seed 11", noise_px=NOISE_PX, n_check=N_CHECK,
               counts=COUNTS, table=table, seconds=round(time.perf_counter() - t0, 1))
    (ROOT / "benchmarks/results/bench_ortho_models.json").write_text(json.dumps(res, indent=1, default=float))
    (ROOT / "benchmarks/results/bench_ortho_models.md").write_text(
        "RMSE in pixels (1 px = 15 m) at GCPs / at 60 independent check points; "
        f"image coordinates with {NOISE_PX} px noise; '-' = fewer GCPs than the model needs.\n\n" + md + "\n")


if __name__ == "__main__":
    main()
