"""What a tile pool's workers cost to start: the fork server with the tile code preloaded
(:func:`stereodem.stereo.runner.pool_context`, the default) against spawned interpreters, in
one run, for 2, 4, 8 and 16 workers.

Each pool runs ``2 × workers`` tiles of a fixed amount of work (box filters of a 256² block,
with the stereo tile code loaded as a real tile needs it; the same for both) through
:func:`stereodem.stereo.runner.run_tiles`, so the CPU seconds that differ between the two are
the workers' start: a spawned worker imports numpy, SciPy, OpenCV, rasterio and pyproj
itself, a forked one inherits them from the server (which imports them once per pool). CPU
seconds are this process's waited-for children (``RUSAGE_CHILDREN``: the spawned workers, or
the fork server and, through it, its workers); medians of ``--repeat`` alternating runs.
Results are checked identical.

    python benchmarks/bench_worker_start.py [--workers 2 4 8 16] [--repeat 3]

writes ``benchmarks/results/bench_worker_start.json``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "benchmarks" / "results" / "bench_worker_start.json"
sys.path.insert(0, str(ROOT / "benchmarks"))

from stereodem.core.jsonutil import dumps as strict_json
from stereodem.stereo import runner  # noqa: E402
from stereodem.stereo.tiling import tile_grid  # noqa: E402


def work_tile(tile, ctx):
    """A fixed amount of OpenCV work per tile (box filters of a 256² float32 block), in a
    process that has the stereo tile code loaded, as every stereo tile needs it
    (:func:`stereodem.stereo.pipeline.process_tile`)."""
    import cv2

    import stereodem.stereo.pipeline  # noqa: F401

    rng = np.random.default_rng(tile.index)
    a = rng.random((256, 256), dtype=np.float32)
    for _ in range(ctx["passes"]):
        a = cv2.boxFilter(a, cv2.CV_32F, (7, 7))
    return {"sum": np.array(float(a.sum()))}


def _children_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one(start: str, workers: int, passes: int):
    """Wall and children-CPU seconds of one pool of ``workers`` over ``2 × workers`` tiles."""
    tiles = tile_grid(16 * 2 * workers, 16, 16)  # 2 x workers tiles
    saved = runner.pool_context
    if start == "spawn":
        runner.pool_context = lambda: multiprocessing.get_context("spawn")
    try:
        c0, t0 = _children_cpu(), time.perf_counter()
        res, fails, _ = runner.run_tiles(work_tile, tiles, {"passes": passes}, workers=workers)
        wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    finally:
        runner.pool_context = saved
    assert not fails, fails
    return wall, cpu, [float(res[k]["sum"]) for k in sorted(res)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", nargs="+", type=int, default=[2, 4, 8, 16])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--passes", type=int, default=20)
    ap.add_argument("--results", default=str(DEST))
    args = ap.parse_args(argv)
    load0 = [round(x, 2) for x in os.getloadavg()]
    rows = []
    for n in args.workers:
        t = {"forkserver": [], "spawn": []}
        sums = {}
        for _ in range(args.repeat):
            for start in ("forkserver", "spawn"):
                wall, cpu, s = one(start, n, args.passes)
                t[start].append((wall, cpu))
                sums[start] = s
        med = {k: np.median(np.array(v), axis=0) for k, v in t.items()}
        row = {
            "workers": n,
            "tiles": 2 * n,
            "forkserver_wall_s": round(float(med["forkserver"][0]), 3),
            "forkserver_cpu_s": round(float(med["forkserver"][1]), 3),
            "spawn_wall_s": round(float(med["spawn"][0]), 3),
            "spawn_cpu_s": round(float(med["spawn"][1]), 3),
            "cpu_saved_per_worker_s": round(float(med["spawn"][1] - med["forkserver"][1]) / n, 3),
            "identical": sums["forkserver"] == sums["spawn"],
        }
        rows.append(row)
        print(json.dumps(row))
    out = {
        "what": "tile pool start: fork server with the tile code preloaded vs spawn, "
        "run_tiles over 2 x workers equal tiles, CPU of waited-for children, medians",
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "node": platform.node(),
        },
        "measured": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "repeat": args.repeat,
        "load_average_before_after": [load0, [round(x, 2) for x in os.getloadavg()]],
        "runs": rows,
    }
    Path(args.results).write_text(strict_json(out, indent=1))
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
