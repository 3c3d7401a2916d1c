"""Where a stereo tile's time goes: ``process_tile`` on tiles of the full simulated granule,
one thread, and PROJ against its local polynomial stand-in (``core/localfit.py``) on one
tile's ground points.

The scene and its configuration are ``bench_scaling.py``'s (run it once first: it writes
``OUT/w1.toml``). The tiles are those ``stereodem run`` makes (captured from
:func:`stereodem.stereo.pipeline.make_dem` through its ``runner`` hook, before any tile runs);
``--tiles`` of them, evenly spaced in the tile order, are each run ``--repeat`` times after
one warm-up call, under a thread budget of 1 (as in a pool worker). Per tile: the median CPU
milliseconds of the whole call and of its parts (rectification, matching, space intersection,
gridding: the tile's own ``seconds`` record, wall clock on one thread). Then, on the first
tile's points, the two coordinate conversions of a tile timed both ways (medians of
``--repeat``): ECEF -> geodetic (the space intersection's) and geodetic -> the DEM's CRS (the
gridding's), with the largest difference between them::

    python benchmarks/bench_tile.py [--out /tmp/bench_scaling] [--tiles 4] [--repeat 5]

writes ``benchmarks/results/bench_tile.json``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "benchmarks" / "results" / "bench_tile.json"


class _Captured(Exception):
    """Raised by the capturing runner once it has the tiles."""


def captured_tiles(cfg_path: Path):
    """``(tiles, inputs, settings)`` of the stereo stage of the job ``cfg_path``."""
    from stereodem.config import load_config
    from stereodem.pipeline.inputs import load_pair
    from stereodem.stereo.pipeline import make_dem

    cfg = load_config(cfg_path)
    pair = load_pair(cfg)
    got = {}

    def runner(fn, tiles, inputs, settings):
        got.update(tiles=tiles, inputs=inputs, settings=settings)
        raise _Captured

    try:
        make_dem(
            pair.left_image,
            pair.right_image,
            pair.left_model,
            pair.right_model,
            cfg.stereo,
            seed_dem=pair.seed_dem,
            runner=runner,
            left_dtype=pair.left_dtype,
            right_dtype=pair.right_dtype,
        )
    except _Captured:
        pass
    return got["tiles"], got["inputs"], got["settings"]


def cpu_ms(fn, repeat):
    """Median CPU milliseconds of ``fn()`` over ``repeat`` calls (after one warm-up call), and
    the last call's result."""
    fn()
    ts = []
    for _ in range(repeat):
        c0 = time.process_time()
        out = fn()
        ts.append(1e3 * (time.process_time() - c0))
    return statistics.median(ts), out


def tile_parts(tile, inputs, settings, repeat):
    from stereodem.stereo.pipeline import process_tile

    parts = {k: [] for k in ("rectify", "match", "intersect", "grid")}
    cpu = []
    process_tile(tile, inputs, settings)
    for _ in range(repeat):
        c0 = time.process_time()
        res = process_tile(tile, inputs, settings)
        cpu.append(1e3 * (time.process_time() - c0))
        for k in parts:
            parts[k].append(1e3 * res.summary["seconds"][k])
    return {
        "tile": int(tile.index),
        "size_px": int(tile.size),
        "n_points": int(res.summary["n_points"]),
        "cpu_ms": round(statistics.median(cpu), 1),
        "cpu_ms_range": [round(min(cpu), 1), round(max(cpu), 1)],
        "parts_ms": {k: round(statistics.median(v), 1) for k, v in parts.items()},
    }


def conversions(tile, inputs, settings, repeat):
    """PROJ vs core.localfit on the tile's ground points."""
    from stereodem.core import geodesy, localfit
    from stereodem.stereo.pipeline import tile_points

    pts = tile_points(tile, inputs, settings)
    lon, lat, h = (np.asarray(a, np.float64) for a in (pts.lon, pts.lat, pts.h))
    x, y, z = (np.asarray(a) for a in geodesy.geodetic_to_ecef(lon, lat, h))
    crs = inputs.lattice.crs
    tol_m = localfit.TILE_TOLERANCE_M
    tol = geodesy.metres_in_crs(tol_m, crs)
    out = {"n_points": int(lon.size), "tolerance_m": tol_m, "crs": str(crs)}
    cases = {
        "ecef_to_geodetic": (
            lambda: geodesy.ecef_to_geodetic(x, y, z),
            lambda: geodesy.ecef_to_geodetic(x, y, z, tolerance_m=tol_m),
        ),
        "geodetic_to_dem_crs": (
            lambda: geodesy.lonlat_to_crs(lon, lat, crs),
            lambda: geodesy.lonlat_to_crs(lon, lat, crs, tolerance=tol),
        ),
    }
    metres = np.array([np.pi / 180 * geodesy.A, np.pi / 180 * geodesy.A, 1.0])
    for name, (exact, fitted) in cases.items():
        t_exact, a = cpu_ms(exact, repeat)
        t_fit, b = cpu_ms(fitted, repeat)
        diffs = [float(np.nanmax(np.abs(np.asarray(p) - np.asarray(q)))) for p, q in zip(a, b)]
        if name == "ecef_to_geodetic":  # degrees, degrees, metres -> metres (upper bounds)
            diffs = [d * m for d, m in zip(diffs, metres)]
        out[name] = {
            "proj_ms": round(t_exact, 2),
            "localfit_ms": round(t_fit, 2),
            "ratio": round(t_exact / t_fit, 2),
            "max_difference_m": [float(f"{d:.3g}") for d in diffs],
        }
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="/tmp/bench_scaling", help="bench_scaling.py's --out")
    ap.add_argument("--tiles", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--results", default=str(DEST))
    args = ap.parse_args(argv)

    import cv2

    from stereodem.core.threads import thread_budget

    cfg = Path(args.out) / "w1.toml"
    if not cfg.exists():
        sys.exit(f"{cfg}: not found; run benchmarks/bench_scaling.py --workers 1 first")
    tiles, inputs, settings = captured_tiles(cfg)
    picks = [tiles[int(i)] for i in np.linspace(0, len(tiles) - 1, args.tiles + 2)[1:-1]]
    with thread_budget(1):
        rows = [tile_parts(t, inputs, settings, args.repeat) for t in picks]
        conv = conversions(picks[0], inputs, settings, args.repeat)
    for r in rows:
        print(
            f"tile {r['tile']:3d}: {r['cpu_ms']:.0f} ms CPU ({r['cpu_ms_range'][0]:.0f}-"
            f"{r['cpu_ms_range'][1]:.0f}), {r['n_points']} points; parts (ms): {r['parts_ms']}"
        )
    for k in ("ecef_to_geodetic", "geodetic_to_dem_crs"):
        c = conv[k]
        print(
            f"{k}: PROJ {c['proj_ms']} ms, localfit {c['localfit_ms']} ms ({c['ratio']}x), "
            f"largest difference (m) {c['max_difference_m']}"
        )
    result = {
        "granule": "bench_scaling.py's full simulated V004 granule, [rectification] tile_size 512",
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "opencv": cv2.__version__,
            "numpy": np.__version__,
        },
        "n_tiles": len(tiles),
        "threads": 1,
        "repeat": args.repeat,
        "tiles": rows,
        "conversions": conv,
        "note": "CPU ms of process_tile (medians); parts from the tile's own seconds record "
        "(wall on one thread); conversions: CPU ms, medians, after one warm-up call",
    }
    Path(args.results).write_text(strict_json(result, indent=1))
    print("wrote", args.results)


if __name__ == "__main__":
    main()
