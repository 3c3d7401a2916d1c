"""Full ASTER-sized scene: the whole DEM (stereo + gridding) on 2 cores, workers 1 vs 2.

Simulates a 3N/3B pair of about 4100 x 4200 (3N) and 5000 x 4600 (3B) pixels from the bundled
SRTM and texture, then runs ``stereodem run`` stages (stereo, post, ortho) with --workers 1
and --workers 2, checks the rasters are bit-identical, and records wall time and peak memory
(this process and the largest worker) per stage. It also measures the matcher's throughput
against ``cv2.StereoSGBM`` on the same epipolar tile, in the same run.

    python benchmarks/bench_aster_scene.py [--size 4100 4200] [--out /tmp/bench_aster]

Writes benchmarks/results/bench_aster_scene.json.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def simulate(out: Path, size):
    from sensor.simulate import simulate_scene, write_scene
    t0 = time.perf_counter()
    sc = simulate_scene("aster", size=tuple(size), seed=0, n_points=100)
    t_sim = time.perf_counter() - t0
    write_scene(sc, out, overwrite=True)
    return t_sim, sc.settings


CONFIG = """[inputs]
left = "{scene}/left.tif"
right = "{scene}/right.tif"
reference_dem = "{scene}/truth_dem.tif"
reference_vertical = "ellipsoid"
[output]
dir = "{out}"
[stereo]
tile_size = 512
height_range = [1000, 3500]
[ortho]
both = false
[assess]
coregister = false
[run]
workers = {workers}
"""


def run_once(scene: Path, out: Path, workers: int):
    cfg = out.with_suffix(".toml")
    cfg.write_text(CONFIG.format(scene=scene, out=out, workers=workers))
    t0 = time.perf_counter()
    r = subprocess.run(["/usr/bin/time", "-v", sys.executable, "-m", "stereodem.cli", "run", str(cfg),
                        "--overwrite"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(r.stderr[-2000:])
    peak_kb = [int(line.split()[-1]) for line in r.stderr.splitlines() if "Maximum resident" in line]
    info = json.loads((out / "run.json").read_text())
    return dict(workers=workers, wall_s=round(wall, 1), peak_rss_mb_max_process=round(peak_kb[0] / 1024, 1),
                stages=info["stages"], headline=info["headline"])


def identical(a: Path, b: Path, names):
    import rasterio
    out = {}
    for n in names:
        with rasterio.open(a / n) as x, rasterio.open(b / n) as y:
            out[n] = bool(np.array_equal(x.read(), y.read(), equal_nan=True))
    return out


def matcher_throughput(scene: Path):
    """ZNCC (ours) vs cv2.StereoSGBM on one rectified 1024x1024 tile of the scene."""
    import cv2
    import rasterio

    from sensor.serialize import load_image_model
    from stereo import epipolar
    from stereo.match import match_rectified
    imgs, models = [], []
    for n in ("left", "right"):
        with rasterio.open(scene / f"{n}.tif") as ds:
            imgs.append(ds.read(1).astype(np.float32))
        models.append(load_image_model(scene / f"{n}.tif"))
    w, h = models[0].width, models[0].height
    tile = epipolar.Tile(w // 2 - 512, h // 2 - 512, 1024, 1024)
    et = epipolar.rectify_tile(models[0], models[1], tile, (1000.0, 3500.0), halo=(0, 0))
    L, R = et.rectify(imgs[0], imgs[1])
    L, R = np.nan_to_num(L), np.nan_to_num(R)
    d0 = int(np.floor(et.disparity_range[0]))
    nd = 64
    res = {}
    for name, kw in (("stereodem ncc coarse-to-fine", dict(matcher="ncc")),
                     ("stereodem ncc full search", dict(matcher="ncc", levels=0)),
                     ("stereodem sgm", dict(matcher="sgm"))):
        t0 = time.perf_counter()
        match_rectified(L, R, (d0, d0 + nd - 1), **kw)
        dt = time.perf_counter() - t0
        res[name] = round(L.size * nd / dt / 1e6, 1)
    l8 = cv2.normalize(L, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    r8 = cv2.normalize(R, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    for name, mode, threads in (("cv2.StereoSGBM 1 thread", cv2.STEREO_SGBM_MODE_SGBM, 1),
                                ("cv2.StereoSGBM 3-way", cv2.STEREO_SGBM_MODE_SGBM_3WAY, 0)):
        cv2.setNumThreads(threads if threads else -1)
        sg = cv2.StereoSGBM_create(minDisparity=d0, numDisparities=nd, blockSize=5, P1=200, P2=800,
                                   mode=mode)
        t0 = time.perf_counter()
        sg.compute(l8, r8)
        dt = time.perf_counter() - t0
        res[name] = round(L.size * nd / dt / 1e6, 1)
    cv2.setNumThreads(-1)
    return dict(tile="1024x1024 epipolar tile at the scene centre", disparities=nd,
                mpx_disparities_per_s=res)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", nargs=2, type=int, default=[4100, 4200])
    ap.add_argument("--out", default="/tmp/bench_aster")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t_sim, settings = simulate(out / "scene", args.size)
    print(f"simulated {args.size} in {t_sim:.1f} s")
    runs = [run_once(out / "scene", out / f"w{w}", w) for w in (1, 2)]
    for r in runs:
        print(f"workers {r['workers']}: {r['wall_s']} s, peak {r['peak_rss_mb_max_process']} MB, "
              f"stereo {r['stages']['stereo']['seconds']} s, NMAD {r['headline']['nmad']:.2f} m")
    same = identical(out / "w1", out / "w2", ["raw/dem.tif", "raw/score.tif", "dem.tif", "ortho_left.tif"])
    mt = matcher_throughput(out / "scene")
    result = dict(size=args.size, simulate_s=round(t_sim, 1), runs=runs, bit_identical=same,
                  speedup_stereo=round(runs[0]["stages"]["stereo"]["seconds"] / runs[1]["stages"]["stereo"]["seconds"], 2),
                  speedup_total=round(runs[0]["wall_s"] / runs[1]["wall_s"], 2), matcher=mt)
    print(json.dumps(dict(bit_identical=same, speedup_stereo=result["speedup_stereo"],
                          speedup_total=result["speedup_total"], matcher=mt), indent=1))
    dest = ROOT / "benchmarks" / "results" / "bench_aster_scene.json"
    dest.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
