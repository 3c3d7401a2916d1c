"""Nuth & Kääb fit on a large DEM: the iterations' translation by one separable cubic filter
against GDAL's cubic warp of the whole DEM (what each iteration did before), same run.

A 3000 x 3000 DEM at 30 m (UTM 37N) of multi-scale Gaussian-filtered noise (relief ~1 km) is
the reference; the DEM to fit is the same surface moved 45 m east and 30 m south by OpenCV's
cubic remap, 3 m up, with 0.5 m of white noise. ``NuthKaab().fit`` runs with each translation,
alternating, ``--repeat`` times at each thread budget; reported: medians of wall and CPU
seconds, their ratio, and the fitted parameters of both (the same fit to well inside its
0.005 px tolerance).

    python benchmarks/bench_nuth_kaab.py [--size 3000] [--repeat 3] [--threads 1 2]

Writes ``benchmarks/results/bench_nuth_kaab.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import time
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
from affine import Affine
from rasterio.crs import CRS

from stereodem.core.dem import DEM
from stereodem.core.jsonutil import dumps as strict_json
from stereodem.core.threads import thread_budget
from stereodem.post import biascorr
from stereodem.post.coreg import CoregChain

OUT = Path(__file__).resolve().parent / "results" / "bench_nuth_kaab.json"
SHIFT_E, SHIFT_N, DZ = 45.0, -30.0, 3.0


def make_pair(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    z = np.zeros((n, n), np.float64)
    for sigma, amp in ((200, 400), (50, 80), (12, 15), (3, 2)):
        f = cv2.GaussianBlur(rng.normal(size=(n, n)), (0, 0), sigma)
        z += amp * f / f.std()
    z += 1500.0
    t = Affine(30.0, 0.0, 400000.0, 0.0, -30.0, 4500000.0)
    crs = CRS.from_epsg(32637)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    # features SHIFT_E east and SHIFT_N north of the reference's: sample the surface there
    moved = cv2.remap(
        z.astype(np.float32),
        xx - SHIFT_E / 30.0,
        yy + SHIFT_N / 30.0,
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    moved += rng.normal(0, 0.5, moved.shape).astype(np.float32) + DZ
    ref = DEM(z.astype(np.float32), t, crs, vertical="ellipsoid")
    return ref, DEM(moved, t, crs, vertical="ellipsoid")


def _gdal_moved(self, dem, east_m, north_m):
    """The iterations' translation before: GDAL's warp of the whole DEM."""
    return biascorr._warp_shift(dem, east_m, north_m, self.resampling)


def fit_once(ref, dem, gdal: bool):
    ctx = mock.patch.object(biascorr.NuthKaab, "_moved", _gdal_moved)
    with ctx if gdal else contextlib.nullcontext():
        w, c = time.perf_counter(), time.process_time()
        chain = CoregChain([biascorr.NuthKaab()]).fit(ref, dem)
        wall, cpu = time.perf_counter() - w, time.process_time() - c
    p = chain.steps[0].params
    return (
        wall,
        cpu,
        {k: p[k]["value"] for k in ("dx", "dy", "dz")} | {"iterations": p["iterations"]},
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args(argv)
    ref, dem = make_pair(args.size)
    load0 = os.getloadavg()
    runs = []
    for n in args.threads:
        with thread_budget(n):
            fit_once(ref, dem, False)  # warm-up (OpenCV's first filter, GDAL's first warp)
            t = {"filter": [], "gdal_warp": []}
            params = {}
            for _ in range(args.repeat):
                for name in t:
                    wall, cpu, p = fit_once(ref, dem, name == "gdal_warp")
                    t[name].append((wall, cpu))
                    params[name] = p
        med = {k: np.median(np.array(v), axis=0) for k, v in t.items()}
        runs.append(
            {
                "threads": n,
                "repeat": args.repeat,
                "filter_wall_s": round(float(med["filter"][0]), 3),
                "filter_cpu_s": round(float(med["filter"][1]), 3),
                "gdal_warp_wall_s": round(float(med["gdal_warp"][0]), 3),
                "gdal_warp_cpu_s": round(float(med["gdal_warp"][1]), 3),
                "speedup_wall": round(float(med["gdal_warp"][0] / med["filter"][0]), 2),
                "cpu_ratio": round(float(med["gdal_warp"][1] / med["filter"][1]), 2),
                "params": params,
                "param_difference_m": {
                    k: round(abs(params["filter"][k] - params["gdal_warp"][k]), 5)
                    for k in ("dx", "dy", "dz")
                },
            }
        )
        print(json.dumps(runs[-1]), flush=True)
    result = {
        "benchmark": "bench_nuth_kaab",
        "issue": 28,
        "what": "NuthKaab().fit on a 3000 x 3000 30 m DEM, injected shift 45 m E / -30 m N, "
        "+3 m: iterations translated by one separable cubic filter vs GDAL's cubic warp of "
        "the whole DEM (before), alternating, medians",
        "size": args.size,
        "injected": {"dx": SHIFT_E, "dy": SHIFT_N, "dz": DZ},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "opencv": cv2.__version__,
        "load_average_before_after": [
            [round(x, 2) for x in load0],
            [round(x, 2) for x in os.getloadavg()],
        ],
        "runs": runs,
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(strict_json(result, indent=2))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
