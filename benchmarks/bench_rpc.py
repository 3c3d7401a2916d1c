"""RPC projection and localisation: stereodem's RPCModel against GDAL's RPC transformer.

One million random points over the real Pleiades test image (1024 x 1024 px) and heights
0-2600 m, timed in the same run (best of ``REPEATS``) for

* ``project`` (ground -> image): ``RPCModel.project`` vs ``RPCTransformer.rowcol``;
* ``localize`` (image -> ground): ``RPCModel.localize`` (Newton to 1e-6 px) vs
  ``RPCTransformer.xy`` with GDAL's default RPC_PIXEL_ERROR_THRESHOLD (0.1 px) and with a
  threshold of 1e-6 px (comparable accuracy).

Accuracy figures (max pixel error of each localisation, through the exact projection) are
reported beside the times. Writes ``benchmarks/results/bench_rpc.json`` and prints a table.

Run: ``python benchmarks/bench_rpc.py``
"""

from __future__ import annotations

import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import RPCTransformer

from stereodem.core.jsonutil import dumps as strict_json
from stereodem.sensor.models.rpc import RPCModel

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "pleiades" / "img_01_rpc.tif"
OUT = ROOT / "benchmarks" / "results" / "bench_rpc.json"
N = 1_000_000
REPEATS = 3


def best_time(fn):
    times, out = [], None
    for _ in range(REPEATS):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def main():
    model = RPCModel.from_file(DATA)
    rng = np.random.default_rng(42)
    col = rng.uniform(0, model.width - 1, N)
    row = rng.uniform(0, model.height - 1, N)
    h = rng.uniform(0.0, 2600.0, N)
    lon, lat = model.localize(col, row, h)  # ground points inside the image
    rpcs = model.to_rasterio()
    res = {
        "n_points": N,
        "repeats": REPEATS,
        "image": str(DATA.relative_to(ROOT)),
        "height_range_m": [0.0, 2600.0],
        "gdal": rasterio.__gdal_version__,
        "rasterio": rasterio.__version__,
        "numpy": np.__version__,
        "machine": f"{platform.machine()} {os.cpu_count()} cpu",
        "python": platform.python_version(),
    }

    # ---- project
    t_ours, (c, r) = best_time(lambda: model.project(lon, lat, h))
    with RPCTransformer(rpcs) as gdal:
        t_gdal, (g_row, g_col) = best_time(
            lambda: gdal.rowcol(lon.copy(), lat.copy(), zs=h.copy(), op=np.positive)
        )
    res["project"] = {
        "ours_s": t_ours,
        "gdal_s": t_gdal,
        "speedup": t_gdal / t_ours,
        "ours_mpts_per_s": N / t_ours / 1e6,
        "gdal_mpts_per_s": N / t_gdal / 1e6,
        # GDAL pixel/line = ours + 0.5 (corner origin)
        "max_abs_diff_px": float(
            max(np.max(np.abs(c - (g_col - 0.5))), np.max(np.abs(r - (g_row - 0.5))))
        ),
    }

    # ---- localize
    t_ours, (o_lon, o_lat) = best_time(lambda: model.localize(col, row, h))
    oc, orow = model.project(o_lon, o_lat, h)
    res["localize"] = {
        "ours_s": t_ours,
        "ours_mpts_per_s": N / t_ours / 1e6,
        "ours_max_err_px": float(np.max(np.hypot(oc - col, orow - row))),
    }
    for label, opts in (("gdal_default", {}), ("gdal_1e-6px", {"RPC_PIXEL_ERROR_THRESHOLD": 1e-6})):
        with RPCTransformer(rpcs, **opts) as gdal, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t_g, (g_lon, g_lat) = best_time(lambda: gdal.xy(row, col, zs=h, offset="center"))
        g_lon, g_lat = np.asarray(g_lon), np.asarray(g_lat)
        ok = np.isfinite(g_lon) & np.isfinite(g_lat)
        gc, gr = model.project(g_lon[ok], g_lat[ok], h[ok])
        res["localize"][label] = {
            "options": opts,
            "gdal_s": t_g,
            "gdal_mpts_per_s": N / t_g / 1e6,
            "speedup": t_g / t_ours,
            "gdal_max_err_px": float(np.max(np.hypot(gc - col[ok], gr - row[ok]))),
            "gdal_failed_points": int((~ok).sum()),
        }

    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(strict_json(res, indent=2))

    p, lz = res["project"], res["localize"]
    print(
        f"RPC benchmark: {N:,} points, Pleiades img_01, heights 0-2600 m, best of {REPEATS} "
        f"(GDAL {res['gdal']}, rasterio {res['rasterio']})"
    )
    print(f"{'operation':<34}{'stereodem s':>12}{'GDAL s':>10}{'speed-up':>10}{'max err px':>22}")
    print(
        f"{'project':<34}{p['ours_s']:>12.3f}{p['gdal_s']:>10.3f}{p['speedup']:>9.1f}x"
        f"{'diff ' + format(p['max_abs_diff_px'], '.1e'):>22}"
    )
    for label in ("gdal_default", "gdal_1e-6px"):
        g = lz[label]
        errors = f"{lz['ours_max_err_px']:.1e} / {g['gdal_max_err_px']:.1e}"
        print(
            f"{'localize vs ' + label:<34}{lz['ours_s']:>12.3f}{g['gdal_s']:>10.3f}"
            f"{g['speedup']:>9.1f}x{errors:>22}"
        )
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
