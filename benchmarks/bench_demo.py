"""``stereodem demo``: run-to-run spread of its accuracy figures and the cost of writing its
rasters as Cloud-Optimised GeoTIFFs.

1. Runs ``stereodem demo`` (600 x 600, the default seed 0) with ``--workers 1`` and
   ``--workers 2``, then with seeds 1..N: the default-seed figures are the ones the README
   quotes; the spread over seeds (the simulator's noise realisation) is the tolerance of
   ``tests/app/test_products_demo.py::test_readme_demo_figures`` (``nmad_tolerance_m``: the
   largest |NMAD(seed k) - NMAD(seed 0)|).
2. Rewrites every raster the demo wrote (``result/**/*.tif``) both ways, ``--repeat`` times:
   the previous layout (GTiff, 256² tiles, DEFLATE, no predictor, no overviews) and the
   current one (:func:`stereodem.core.raster.write_geotiff`: COG, predictor, overviews),
   and reports the extra seconds against the demo's own run time (the fastest of the runs
   above, the least disturbed on shared cores; target <= 10 %) and the file sizes.

    python benchmarks/bench_demo.py [--seeds 4] [--repeat 3] [--out /tmp/bench_demo]

Needs the ``bench`` extra (``pip install -e .[bench]``). Writes
benchmarks/results/bench_demo.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]


def run_demo(out: Path, seed: int, workers: int) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "stereodem.cli",
        "demo",
        "-o",
        str(out),
        "--seed",
        str(seed),
        "--workers",
        str(workers),
        "--overwrite",
    ]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    info = json.loads((out / "result" / "run.json").read_text())
    h = info["headline"]
    return {
        "seed": seed,
        "workers": workers,
        "wall_seconds": round(wall, 2),
        "pipeline_seconds": info["seconds"],
        "nmad_m": h["nmad"],
        "median_m": h["median"],
        "rmse_m": h["rmse"],
        "le90_m": h["le90"],
        "valid_pct": h["valid_pct"],
        "stages_seconds": {k: v["seconds"] for k, v in info["stages"].items()},
    }


def old_layout_write(path, arr, profile):
    """The layout before issue #19: GTiff, 256² tiles when large enough, DEFLATE, no predictor,
    no overviews."""
    import rasterio

    p = dict(
        driver="GTiff",
        width=arr.shape[2],
        height=arr.shape[1],
        count=arr.shape[0],
        dtype=arr.dtype,
        crs=profile["crs"],
        transform=profile["transform"],
        nodata=profile["nodata"],
        compress="deflate",
        tiled=arr.shape[1] >= 256 and arr.shape[2] >= 256,
    )
    if p["tiled"]:
        p.update(blockxsize=256, blockysize=256)
    with rasterio.open(path, "w", **p) as dst:
        dst.write(arr)


def writing_cost(result_dir: Path, repeat: int) -> dict:
    import rasterio

    from stereodem.core.raster import write_geotiff

    rasters = sorted(result_dir.rglob("*.tif"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for r in rasters:
            with rasterio.open(r) as ds:
                arr, prof = ds.read(), ds.profile
                vertical = ds.tags().get("STEREODEM_VERTICAL")
            t_old, t_new = [], []
            for k in range(repeat):
                a, b = tmp / f"old{k}.tif", tmp / f"new{k}.tif"
                t0 = time.perf_counter()
                old_layout_write(a, arr, prof)
                t_old.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                write_geotiff(
                    b,
                    arr,
                    prof["transform"],
                    prof["crs"],
                    prof["nodata"],
                    vertical=vertical,
                    overwrite=True,
                )
                t_new.append(time.perf_counter() - t0)
            rows.append(
                {
                    "raster": str(r.relative_to(result_dir)),
                    "dtype": str(arr.dtype),
                    "shape": list(arr.shape[1:]),
                    "old_seconds": round(float(np.median(t_old)), 4),
                    "cog_seconds": round(float(np.median(t_new)), 4),
                    "old_bytes": a.stat().st_size,
                    "cog_bytes": b.stat().st_size,
                }
            )
    return {
        "rasters": rows,
        "old_seconds": round(sum(r["old_seconds"] for r in rows), 4),
        "cog_seconds": round(sum(r["cog_seconds"] for r in rows), 4),
        "old_bytes": sum(r["old_bytes"] for r in rows),
        "cog_bytes": sum(r["cog_bytes"] for r in rows),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=4, help="extra seeds after 0 (default 4)")
    ap.add_argument("--repeat", type=int, default=3, help="writes per raster and layout")
    ap.add_argument("--out", default="/tmp/bench_demo")
    a = ap.parse_args(argv)
    out = Path(a.out)
    runs = [run_demo(out / "w1", 0, 1), run_demo(out / "w2", 0, 2)]
    for s in range(1, a.seeds + 1):
        runs.append(run_demo(out / f"s{s}", s, 1))
        shutil.rmtree(out / f"s{s}", ignore_errors=True)
    base = runs[0]
    others = [r for r in runs if r["seed"] != 0]
    spread = {
        k: round(max(abs(r[k] - base[k]) for r in others), 3) if others else 0.0
        for k in ("nmad_m", "le90_m", "median_m")
    }
    cost = writing_cost(out / "w1" / "result", a.repeat)
    extra = cost["cog_seconds"] - cost["old_seconds"]
    fastest = min(r["wall_seconds"] for r in runs)  # the least disturbed run (shared cores)
    res = {
        "what": "stereodem demo (600x600, seed 0): figures, run-to-run spread, COG writing cost",
        "machine": f"{platform.node()} ({platform.processor() or platform.machine()}), "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the end",
        "python": sys.version.split()[0],
        "default_seed_figures": {
            k: base[k]
            for k in (
                "nmad_m",
                "median_m",
                "le90_m",
                "rmse_m",
                "valid_pct",
                "wall_seconds",
                "pipeline_seconds",
            )
        },
        "workers_1_vs_2_identical_nmad": runs[0]["nmad_m"] == runs[1]["nmad_m"],
        "spread_over_seeds": spread,
        "nmad_tolerance_m": spread["nmad_m"],
        "runs": runs,
        "cog_writing": dict(
            cost,
            extra_seconds=round(extra, 4),
            fastest_demo_wall_seconds=fastest,
            extra_fraction_of_demo_wall=round(extra / fastest, 4),
            cog_fraction_of_demo_wall=round(cost["cog_seconds"] / fastest, 4),
            target="extra <= 10 % of the demo's run time",
        ),
    }
    dst = ROOT / "benchmarks" / "results" / "bench_demo.json"
    dst.write_text(strict_json(res, indent=1))
    print(json.dumps({k: res[k] for k in ("default_seed_figures", "spread_over_seeds")}, indent=1))
    c = res["cog_writing"]
    print(
        f"COG writing: {c['cog_seconds']:.3f} s vs old {c['old_seconds']:.3f} s: "
        f"+{c['extra_seconds']:.3f} s = {100 * c['extra_fraction_of_demo_wall']:.1f} % of the "
        f"fastest demo run's {fastest:.1f} s; bytes {c['old_bytes']} -> {c['cog_bytes']}"
    )
    print(f"wrote {dst}")


if __name__ == "__main__":
    main()
