"""Orun & Natarajan and the Toutin-type model against the rigorous pushbroom model on the
simulated ASTER 3N and 3B views, over random GCP/ICP splits, for GCP counts from few to many.

Scene: :func:`stereodem.sensor.simulation.control_points.aster_pair_scene` (the simulator's
full-size ASTER pair geometry over the bundled DEM); the truths carry attitude biases and
drifts and position offsets against the metadata models. Points: random pixels of the truth
localised on the DEM, image coordinates with 0.3 px of Gaussian noise. For each of N_SPLITS
random splits (60 check points, the rest a GCP pool in random order) every model is adjusted
with the first n GCPs through the adjustment engine
(:func:`stereodem.sensor.estimation.compare.compare_splits`; the registered sets, with their
weighted parameters). Reported per model and GCP count: the median and the largest ratio of
ICP RMSE to the rigorous model's (``attitude-bias-drift``) at the same split, the median ICP
RMSE and the median condition number (column-equilibrated normal matrix).

    python benchmarks/bench_orbital_splits.py

Writes benchmarks/results/bench_orbital_splits.json and .md.
"""

from __future__ import annotations

import time
from pathlib import Path

from stereodem.core.jsonutil import dumps as strict_json
from stereodem.sensor.estimation.compare import compare_splits, split_summary
from stereodem.sensor.simulation.control_points import (
    aster_pair_scene,
    points_at_pixels,
    random_pixels,
    to_control_points,
)

ROOT = Path(__file__).resolve().parents[1]
COUNTS = (4, 5, 6, 8, 10, 15, 20)
MODELS = ("orun", "toutin", "orun-full", "toutin-full")
REFERENCE = "attitude-bias-drift"
N_SPLITS = 9
N_CHECK = 60
NOISE_PX = 0.3


def main():
    t0 = time.perf_counter()
    nadir, back, truth_n, truth_b, dem = aster_pair_scene()
    out = {}
    for label, meta, truth in (("3N", nadir, truth_n), ("3B", back, truth_b)):
        pts = points_at_pixels(
            truth, dem, *random_pixels(truth, 200, seed=1), noise_px=NOISE_PX, seed=1
        )
        recs = compare_splits(
            meta,
            to_control_points(pts, "gcp"),
            MODELS,
            COUNTS,
            reference=REFERENCE,
            n_check=N_CHECK,
            n_splits=N_SPLITS,
            sigma_px=NOISE_PX,
        )
        out[label] = dict(records=recs, summary=split_summary(recs))
    seconds = round(time.perf_counter() - t0, 1)
    md = markdown(out)
    print(md)
    res = dict(
        scene="aster_pair_scene (3N 4100x4200, 3B 5000x4600), truth = metadata with "
        "TRUTH_ERRORS / TRUTH_ERRORS_BACKWARD",
        noise_px=NOISE_PX,
        n_check=N_CHECK,
        n_splits=N_SPLITS,
        counts=COUNTS,
        reference=REFERENCE,
        views={k: v["summary"] for k, v in out.items()},
        records={k: v["records"] for k, v in out.items()},
        seconds=seconds,
        note="timings under contention (2 cores shared by several jobs)",
    )
    dest = ROOT / "benchmarks/results"
    (dest / "bench_orbital_splits.json").write_text(strict_json(res, indent=1))
    (dest / "bench_orbital_splits.md").write_text(
        f"ICP RMSE of each model over the rigorous model's ({REFERENCE}, 6 parameters) on the "
        f"same split: median and largest over {N_SPLITS} random splits ({N_CHECK} check points, "
        f"{NOISE_PX} px image noise); median ICP RMSE (px) and median condition number; "
        "'refused' = too few GCPs for the set (the count needed is in the JSON).\n\n" + md
    )


def markdown(out) -> str:
    lines = []
    for label, v in out.items():
        lines += [
            f"### ASTER {label}",
            "",
            "| model | u | GCPs | median ratio | max ratio | median ICP px | median condition |",
            "|---|---|---|---|---|---|---|",
        ]
        for s in v["summary"]:
            if s["refused"] == s["splits"]:
                lines.append(f"| {s['model']} | {s['n_params']} | {s['n_gcp']} | refused | | | |")
                continue
            lines.append(
                f"| {s['model']} | {s['n_params']} | {s['n_gcp']} | {s['median_ratio']:.2f} | "
                f"{s['max_ratio']:.2f} | {s['median_icp_px']:.2f} | "
                f"{s['median_condition']:.3g} |"
            )
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
