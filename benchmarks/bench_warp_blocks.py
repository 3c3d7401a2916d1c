"""Blockwise warps between two CRSs: the source read in place (now) against the whole source
written into an in-memory GeoTIFF at every block (before, ``tests/helpers/warp_before.py``),
same run.

The case: an N x N DEM at 30 m on UTM 33N at 78 N (multi-scale Gaussian-filtered noise, relief
about 1 km, voids) assessed against an N x N reference at 30 m on EPSG:3413 (polar
stereographic: turned by about 58 degrees against it; the DEM warped onto it, plus noise) by
``post.assess.blockwise_comparison`` in its blocks of ``BLOCK_ROWS`` reference rows. Each
run is a fresh process: the data made, a warm-up comparison on a 64-row strip, then the
baseline; reported: wall and CPU seconds and the peak resident memory above the baseline
(``VmHWM``, reset at the baseline), before and now alternating, ``--repeat`` times at each
thread count. The statistics of both must be the same (compared as JSON). Then one block's
warp (``BLOCK_ROWS`` x ``BLOCK_ROWS`` cells of the reference grid, inside the DEM) against the
size of the DEM (``--sources``, up to 16000 x 16000 cells, 1 GB): before and now alternating
in one process, medians of ``--repeat`` of the time and of the peak memory above the call's
start.

    python benchmarks/bench_warp_blocks.py [--size 4000] [--repeat 3] [--threads 1 2]
        [--sources 1000 4000 16000] [--skip-assessment]

Writes ``benchmarks/results/bench_warp_blocks.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the former reading: tests/helpers/warp_before.py

from helpers.warp_before import reading_as_before  # noqa: E402

from stereodem.core import geodesy, warp  # noqa: E402
from stereodem.core.dem import DEM  # noqa: E402
from stereodem.core.jsonutil import dumps as strict_json  # noqa: E402
from stereodem.post import assess  # noqa: E402
from stereodem.stereo.runner import process_peak_rss_mb, reset_peak_rss  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_warp_blocks.json"
RES = 30.0


def make_dem(n: int, seed: int = 0) -> DEM:
    """An n x n DEM at 30 m on UTM 33N, its north-west corner at 500 km E, 8700 km N (78 N)."""
    rng = np.random.default_rng(seed)
    z = np.zeros((n, n), np.float32)
    for sigma, amp in ((n / 20, 400), (n / 80, 80), (3, 15)):
        f = cv2.GaussianBlur(rng.normal(size=(n, n)).astype(np.float32), (0, 0), sigma)
        z += np.float32(amp) * f / f.std()
    z += 800.0
    z[n // 3 : n // 3 + n // 40, n // 2 : n // 2 + n // 30] = np.nan  # a void
    t = Affine(RES, 0, 500000.0, 0, -RES, 8700000.0)
    return DEM(z, t, "EPSG:32633", "geoid", "dem.tif")


def polar_grid(dem: DEM, n: int) -> Affine:
    """An n x n grid at 30 m on EPSG:3413 centred on the DEM."""
    x, y = dem.transform @ (dem.shape[1] / 2, dem.shape[0] / 2)
    cx, cy = geodesy.transformer("EPSG:32633", "EPSG:3413").transform(x, y)
    return Affine(RES, 0, cx - RES * n / 2, 0, -RES, cy + RES * n / 2)


def make_pair(n: int):
    dem = make_dem(n)
    t = polar_grid(dem, n)
    z = warp.to_grid(dem.heights, dem.transform, dem.crs, t, "EPSG:3413", (n, n), threads=2)
    z += np.random.default_rng(1).normal(0, 0.5, z.shape).astype(np.float32)
    return dem, DEM(z, t, "EPSG:3413", "geoid", "reference.tif")


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0


def child(kind: str, n: int, threads: int) -> dict:
    """One measured assessment in this (fresh) process."""
    dem, ref = make_pair(n)
    ctx = reading_as_before() if kind == "before" else contextlib.nullcontext()
    with ctx:
        strip = DEM(ref.heights[n // 2 : n // 2 + 64].copy(), ref.transform, ref.crs, "geoid")
        assess.blockwise_comparison(dem, strip, threads=threads)  # GDAL, PROJ, pools loaded
        base = _rss_mb()
        reset_peak_rss()
        w, c = time.perf_counter(), time.process_time()
        stats, _, _ = assess.blockwise_comparison(dem, ref, threads=threads)
        wall, cpu = time.perf_counter() - w, time.process_time() - c
    return dict(
        kind=kind,
        threads=threads,
        wall_s=wall,
        cpu_s=cpu,
        baseline_rss_mb=base,
        peak_above_baseline_mb=process_peak_rss_mb() - base,
        stats=json.loads(strict_json(stats["stats"])),
    )


def run_child(kind: str, n: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--child", kind, "--size", str(n), "--threads", str(threads)]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
    if p.returncode:
        raise RuntimeError(f"{kind} {threads}: {p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def plain_dem(n: int) -> DEM:
    """An n x n DEM at 30 m like :func:`make_dem`'s, a smooth surface plus white noise (made
    in seconds at 16000 x 16000)."""
    x = np.arange(n, dtype=np.float32) * np.float32(RES)
    z = np.random.default_rng(2).standard_normal((n, n), dtype=np.float32)
    z += 800 + 300 * np.sin(x / 5000)[None, :] * np.cos(x / 7000)[:, None]
    return DEM(z, Affine(RES, 0, 500000.0, 0, -RES, 8700000.0), "EPSG:32633", "geoid")


def block_costs(block: int, sizes, repeat: int) -> list[dict]:
    """One block's warp (``block`` x ``block`` cells of the reference grid, on the middle of
    the DEM, inside it) against the size of the DEM, before and now alternating: wall
    seconds and the peak resident memory above the call's start (``VmHWM``, reset there)."""
    rows = []
    for s in sizes:
        dem = plain_dem(s)
        t = polar_grid(dem, block)
        args = (dem.heights, dem.transform, dem.crs, t, "EPSG:3413", (block, block))
        times = {"before": [], "now": []}
        peaks = {"before": [], "now": []}
        outs = {}
        for i in range(repeat):
            for kind in ("before", "now") if i % 2 == 0 else ("now", "before"):
                ctx = reading_as_before() if kind == "before" else contextlib.nullcontext()
                outs.pop(kind, None)
                with ctx:
                    base = _rss_mb()
                    reset_peak_rss()
                    w = time.perf_counter()
                    outs[kind] = warp.to_grid(*args)
                    times[kind].append(time.perf_counter() - w)
                    peaks[kind].append(process_peak_rss_mb() - base)
        assert np.isfinite(outs["now"]).all()  # the block lies inside the DEM
        rows.append(
            dict(
                source_cells=s * s,
                source_mb=dem.heights.nbytes / 2**20,
                before_s=statistics.median(times["before"]),
                now_s=statistics.median(times["now"]),
                before_peak_mb=statistics.median(peaks["before"]),
                now_peak_mb=statistics.median(peaks["now"]),
                identical=bool(np.array_equal(outs["before"], outs["now"], equal_nan=True)),
            )
        )
        print(json.dumps(rows[-1]), flush=True)
        del dem, args, outs
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--sources", type=int, nargs="+", default=[1000, 4000, 16000])
    ap.add_argument("--skip-assessment", action="store_true", help="only the block costs")
    ap.add_argument("--child", choices=["before", "now"], help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.size, a.threads[0])))
        return
    runs = []
    for threads in [] if a.skip_assessment else a.threads:
        for i in range(a.repeat):
            for kind in ("before", "now") if i % 2 == 0 else ("now", "before"):
                r = run_child(kind, a.size, threads)
                runs.append(r)
                print(json.dumps({k: v for k, v in r.items() if k != "stats"}), flush=True)
    blocks = block_costs(assess.BLOCK_ROWS, a.sources, a.repeat)
    if a.skip_assessment:
        return
    same = all(r["stats"] == runs[0]["stats"] for r in runs)
    summary = []
    for threads in a.threads:
        by = {
            k: [r for r in runs if r["threads"] == threads and r["kind"] == k]
            for k in ("before", "now")
        }
        med = {
            k: {m: statistics.median(r[m] for r in v) for m in ("wall_s", "cpu_s")}
            | {"peak_above_baseline_mb": statistics.median(r["peak_above_baseline_mb"] for r in v)}
            for k, v in by.items()
        }
        summary.append(dict(threads=threads, **med))
    result = dict(
        size=a.size,
        block_rows=assess.BLOCK_ROWS,
        repeat=a.repeat,
        statistics_identical=same,
        stats=runs[0]["stats"],
        summary=summary,
        runs=[{k: v for k, v in r.items() if k != "stats"} for r in runs],
        block_costs=blocks,
        machine=dict(
            cpus=os.cpu_count(),
            load_average=list(os.getloadavg()),
            python=platform.python_version(),
            numpy=np.__version__,
            rasterio=rasterio.__version__,
            gdal=rasterio.__gdal_version__,
        ),
    )
    OUT.write_text(strict_json(result, indent=1))
    print(json.dumps(summary, indent=1))
    print(f"statistics identical: {same}; wrote {OUT}")


if __name__ == "__main__":
    main()
