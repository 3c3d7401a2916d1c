"""Full ASTER granule on 2 cores: ``stereodem dem`` and ``stereodem run``, workers 1 vs 2.

Simulates a 3N/3B pair of real ASTER size (3N 4100 x 4200, 3B 5000 x 5400 pixels, the real
granule's pointing and timing: the ``aster`` preset) over the bundled SRTM extended by
mirroring (the 1000 x 1000 3" tile is too small for a full scene: it is reflected 300 cells
on each side, which keeps real relief and continuous heights), writes it as an ASTER L1A V004
granule, then

* runs ``stereodem dem GRANULE`` and ``stereodem run`` on the granule (stereo, post, both
  orthoimages, assessment against the simulator's truth; issue #14's target: <= 45 s,
  <= 2.5 GB) with ``--workers 1`` and ``--workers 2``;
* records wall time, CPU seconds (user + system of the job and all its worker processes) and
  peak memory, summed over the process and its workers (sampled every 0.2 s with psutil), per
  run, and the per-stage figures of ``run.json``: wall seconds, CPU seconds of the main
  process (``cpu_s``, all its threads) and of the tile workers (``worker_cpu_s``), the main
  process's peak resident memory during the stage and the tile processes' peak; the
  machine's load average is stored with each run (it is shared: compare CPU seconds);
* checks that the rasters of the two worker counts are bit-identical;
* measures the matcher's throughput against ``cv2.StereoSGBM`` on the same epipolar tile, in
  the same run.

    python benchmarks/bench_aster_scene.py [--size 4100 4200] [--right-size 5000 5400]
                                           [--out /tmp/bench_aster] [--resimulate]
                                           [--run-workers N [N ...]]

``--run-workers`` re-measures only the ``stereodem run`` jobs of those worker counts (no
``stereodem dem`` runs, no matcher comparison) and updates their entries in the existing
results file (the rasters are compared with the other worker count's output folder when it is
there).

The simulated scene is kept in ``OUT/scene`` and reused when its sizes match. Writes
benchmarks/results/bench_aster_scene.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]
MIRROR_CELLS = 300


def mirrored_dem(pad=MIRROR_CELLS):
    """The bundled SRTM reflected ``pad`` cells on every side (same posting, EGM96 heights)."""
    from affine import Affine

    from stereodem.core.dem import DEM

    d = DEM.bundled()
    z = np.pad(d.heights, pad, mode="reflect")
    t = d.transform @ Affine.translation(-pad, -pad)
    return DEM(z, t, d.crs, d.vertical, str(d.path) + f" (mirrored by {pad} cells)")


def simulate(out: Path, size, right_size, force=False):
    """Simulate the scene and write it twice: GeoTIFFs + model sidecars (for the matcher
    benchmark) and an ASTER L1A V004 granule, the input the jobs below read."""
    from stereodem.sensor.simulation.aster_granule import write_granule_scene
    from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

    meta = out / "scene.json"
    if meta.exists() and not force and list(out.glob("AST_L1A_*.hdf")):
        s = json.loads(meta.read_text())["settings"]
        if s.get("size") == list(size) and s.get("right_size") == list(right_size):
            print(f"reusing the simulated scene in {out}")
            return None, None
    t0 = time.perf_counter()
    sc = simulate_scene(
        "aster",
        size=tuple(size),
        right_size=tuple(right_size),
        dem=mirrored_dem(),
        seed=0,
        n_points=100,
    )
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    write_granule_scene(sc, out, version=4, seed=0, overwrite=True)
    t_granule = time.perf_counter() - t0
    write_scene(sc, out, overwrite=True)
    return t_sim, t_granule


def granule(scene: Path) -> Path:
    return sorted(scene.glob("AST_L1A_*.hdf"))[0]


def measured(cmd):
    """Run ``cmd``; returns (wall s, peak RSS MB summed over the process tree, stderr, CPU s
    of the process and every descendant it waited for)."""
    import resource

    import psutil

    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc, peak = psutil.Process(p.pid), 0
    while p.poll() is None:
        try:
            tree = [proc] + proc.children(recursive=True)
            peak = max(peak, sum(q.memory_info().rss for q in tree if q.is_running()))
        except psutil.Error:
            pass
        time.sleep(0.2)
    out, err = p.communicate()
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{err[-3000:]}")
    return wall, peak / 2**20, err, cpu


CONFIG = """[inputs]
left = "{granule}"
reference_dem = "{scene}/truth_dem.tif"
reference_vertical = "ellipsoid"
[output]
dir = "{out}"
[rectification]
tile_size = 512
height_range = [1000, 3500]
[ortho]
both = true
[assess]
coregister = false
[run]
workers = {workers}
"""


def dem_once(scene: Path, out: Path, workers: int):
    cmd = [
        sys.executable,
        "-m",
        "stereodem.cli",
        "-q",
        "dem",
        str(granule(scene)),
        "-o",
        str(out),
        "--height-range",
        "1000",
        "3500",
        "--workers",
        str(workers),
        "--overwrite",
    ]
    load = os.getloadavg()[0]
    wall, peak, _, cpu = measured(cmd)
    rep = json.loads((out / "dem_report.json").read_text())
    return dict(
        workers=workers,
        wall_s=round(wall, 1),
        cpu_s=round(cpu, 1),
        load_average_at_start=round(load, 2),
        peak_rss_mb_all_processes=round(peak),
        stereo_s=round(rep["seconds"], 1),
        n_points=rep["n_points"],
        valid_cells=rep["info"]["valid_cells"],
        failed_tiles=len(rep["failed_tiles"]),
    )


def run_once(scene: Path, out: Path, workers: int):
    cfg = out.with_suffix(".toml")
    cfg.write_text(CONFIG.format(scene=scene, granule=granule(scene), out=out, workers=workers))
    load = os.getloadavg()[0]
    wall, peak, _, cpu = measured(
        [sys.executable, "-m", "stereodem.cli", "-q", "run", str(cfg), "--overwrite"]
    )
    info = json.loads((out / "run.json").read_text())
    return dict(
        workers=workers,
        wall_s=round(wall, 1),
        cpu_s=round(cpu, 1),
        load_average_at_start=round(load, 2),
        load_average_at_end=round(os.getloadavg()[0], 2),
        peak_rss_mb_all_processes=round(peak),
        stages=info["stages"],
        stage_table=stage_table(info["stages"]),
        headline=info["headline"],
    )


def stage_table(stages) -> list:
    """One row per stage: wall s, CPU s (main process, tile workers), peak MB (main process
    during the stage, largest tile process)."""
    rows = []
    for name, st in stages.items():
        rows.append(
            dict(
                stage=name,
                wall_s=st["seconds"],
                cpu_s=st.get("cpu_s"),
                worker_cpu_s=st.get("worker_cpu_s"),
                main_peak_rss_mb=st["peak_rss_mb"],
                peak_scope=st.get("peak_rss_scope", "process"),
                tile_process_peak_rss_mb=st.get("tile_process_peak_rss_mb"),
            )
        )
    return rows


def print_stage_table(run):
    print(
        f"  {'stage':8s} {'wall s':>7s} {'CPU s':>7s} {'workers CPU s':>14s} {'main peak MB':>13s}"
    )
    for r in run["stage_table"]:
        print(
            f"  {r['stage']:8s} {r['wall_s']:7.1f} {r['cpu_s'] or 0:7.1f} "
            f"{r['worker_cpu_s'] or 0:14.1f} {r['main_peak_rss_mb']:13.0f}"
        )


def identical(a: Path, b: Path, names):
    import rasterio

    out = {}
    for n in names:
        with rasterio.open(a / n) as x, rasterio.open(b / n) as y:
            out[n] = bool(np.array_equal(x.read(), y.read(), equal_nan=True))
    return out


def matcher_throughput(scene: Path):
    """Our matchers vs cv2.StereoSGBM on one rectified 1024 x 1024 tile of the scene."""
    import cv2
    import rasterio

    from stereodem.sensor.io.sidecar import load_image_model
    from stereodem.stereo import epipolar
    from stereodem.stereo.match import match_rectified
    from stereodem.stereo.tiling import Tile

    imgs, models = [], []
    for n in ("left", "right"):
        with rasterio.open(scene / f"{n}.tif") as ds:
            imgs.append(ds.read(1).astype(np.float32))
        models.append(load_image_model(scene / f"{n}.tif"))
    w, h = models[0].width, models[0].height
    tile = Tile(w // 2 - 512, h // 2 - 512, 1024, 1024)
    et = epipolar.rectify_tile(models[0], models[1], tile, (1000.0, 3500.0), halo=(0, 0))
    L, R = et.rectify(imgs[0], imgs[1])
    L, R = np.nan_to_num(L), np.nan_to_num(R)
    d0 = int(np.floor(et.disparity_range[0]))
    nd = 64
    res = {}
    for name, kw in (
        ("stereodem ncc coarse-to-fine", dict(matcher="ncc")),
        ("stereodem ncc full search", dict(matcher="ncc", levels=0)),
        ("stereodem sgm", dict(matcher="sgm")),
    ):
        t0 = time.perf_counter()
        match_rectified(L, R, (d0, d0 + nd - 1), **kw)
        dt = time.perf_counter() - t0
        res[name] = round(L.size * nd / dt / 1e6, 1)
    l8 = cv2.normalize(L, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    r8 = cv2.normalize(R, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    for name, mode, threads in (
        ("cv2.StereoSGBM 1 thread", cv2.STEREO_SGBM_MODE_SGBM, 1),
        ("cv2.StereoSGBM 3-way", cv2.STEREO_SGBM_MODE_SGBM_3WAY, 0),
    ):
        cv2.setNumThreads(threads if threads else -1)
        sg = cv2.StereoSGBM_create(
            minDisparity=d0, numDisparities=nd, blockSize=5, P1=200, P2=800, mode=mode
        )
        t0 = time.perf_counter()
        sg.compute(l8, r8)
        dt = time.perf_counter() - t0
        res[name] = round(L.size * nd / dt / 1e6, 1)
    cv2.setNumThreads(-1)
    return dict(
        tile="1024x1024 epipolar tile at the scene centre",
        disparities=nd,
        mpx_disparities_per_s=res,
    )


RUN_LAYERS = ["raw/dem.tif", "raw/score.tif", "dem.tif", "ortho_left.tif", "ortho_right.tif"]


def rerun(out: Path, workers):
    """Re-measure the ``stereodem run`` jobs of ``workers`` and update their entries (and the
    bit-identity check) in the results file."""
    dest = ROOT / "benchmarks" / "results" / "bench_aster_scene.json"
    result = json.loads(dest.read_text())
    runs = {r["workers"]: r for r in result.get("runs", [])}
    for w in workers:
        shutil.rmtree(out / f"w{w}", ignore_errors=True)
        r = run_once(out / "scene", out / f"w{w}", w)
        r["measured"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        runs[w] = r
        print(
            f"stereodem run workers {w}: {r['wall_s']} s wall, {r['cpu_s']} CPU s, peak "
            f"{r['peak_rss_mb_all_processes']} MB, NMAD {r['headline']['nmad']:.2f} m, "
            f"{r['headline']['valid_pct']:.2f} % valid (load average {r['load_average_at_start']})"
        )
        print_stage_table(r)
    result["runs"] = [runs[w] for w in sorted(runs)]
    result["runs_note"] = (
        "runs re-measured with --run-workers (see each run's 'measured'); "
        "dem_runs and matcher are from the last full bench run"
    )
    if set(workers) >= {1, 2} or all((out / f"w{w}" / "dem.tif").exists() for w in (1, 2)):
        same = identical(out / "w1", out / "w2", RUN_LAYERS)
        result.setdefault("bit_identical", {})["run"] = same
        print("bit-identical rasters, workers 1 vs 2:", same)
    if 1 in runs and 2 in runs:
        result.update(
            speedup_stereo=round(
                runs[1]["stages"]["stereo"]["seconds"] / runs[2]["stages"]["stereo"]["seconds"], 2
            ),
            speedup_total=round(runs[1]["wall_s"] / runs[2]["wall_s"], 2),
        )
    dest.write_text(strict_json(result, indent=1))
    print(f"updated {dest}")


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--size", nargs=2, type=int, default=[4100, 4200])
    ap.add_argument("--right-size", nargs=2, type=int, default=[5000, 5400])
    ap.add_argument("--out", default="/tmp/bench_aster")
    ap.add_argument("--resimulate", action="store_true")
    ap.add_argument("--skip-run", action="store_true", help="only the stereodem dem runs")
    ap.add_argument(
        "--run-workers",
        nargs="+",
        type=int,
        default=None,
        help="re-measure only these `stereodem run` worker counts; update the results file",
    )
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_sim, t_granule = simulate(out / "scene", args.size, args.right_size, args.resimulate)
    if args.run_workers:
        return rerun(out, args.run_workers)
    from machine_speed import WHAT, speed_index

    speed_before = speed_index()
    if t_sim is not None:
        print(
            f"simulated {args.size} + {args.right_size} in {t_sim:.1f} s, granule written in "
            f"{t_granule:.1f} s"
        )
    dem_runs = []
    for w in (1, 2):
        shutil.rmtree(out / f"dem_w{w}", ignore_errors=True)
        dem_runs.append(dem_once(out / "scene", out / f"dem_w{w}", w))
        print("stereodem dem", dem_runs[-1])
    same = {
        "dem": identical(
            out / "dem_w1", out / "dem_w2", ["dem.tif", "score.tif", "count.tif", "raygap.tif"]
        )
    }
    result = dict(
        input="ASTER L1A V004 granule",
        size=args.size,
        right_size=args.right_size,
        simulate_s=None if t_sim is None else round(t_sim, 1),
        granule_write_s=None if t_granule is None else round(t_granule, 1),
        dem_mirrored_cells=MIRROR_CELLS,
        dem_runs=dem_runs,
        speedup_dem=round(dem_runs[0]["wall_s"] / dem_runs[1]["wall_s"], 2),
    )
    if not args.skip_run:
        runs = []
        for w in (1, 2):
            shutil.rmtree(out / f"w{w}", ignore_errors=True)
            runs.append(run_once(out / "scene", out / f"w{w}", w))
            r = runs[-1]
            print(
                f"stereodem run workers {w}: {r['wall_s']} s wall, {r['cpu_s']} CPU s, peak "
                f"{r['peak_rss_mb_all_processes']} MB, NMAD {r['headline']['nmad']:.2f} m, "
                f"{r['headline']['valid_pct']:.2f} % valid (load average "
                f"{r['load_average_at_start']})"
            )
            print_stage_table(r)
        same["run"] = identical(out / "w1", out / "w2", RUN_LAYERS)
        result.update(
            runs=runs,
            speedup_stereo=round(
                runs[0]["stages"]["stereo"]["seconds"] / runs[1]["stages"]["stereo"]["seconds"], 2
            ),
            speedup_total=round(runs[0]["wall_s"] / runs[1]["wall_s"], 2),
        )
    result["bit_identical"] = same
    result["machine"] = dict(
        cpus=os.cpu_count(),
        python=platform.python_version(),
        node=platform.node(),
        speed_index_ms=[speed_before, speed_index()],
        speed_index=WHAT,
    )
    result["measured"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    result["note"] = (
        "wall seconds depend on the machine's load (load_average_*: 2 cores shared "
        "with other jobs); CPU seconds per stage are the figures to compare"
    )
    result["matcher"] = matcher_throughput(out / "scene")
    print(json.dumps({k: result[k] for k in ("bit_identical", "speedup_dem", "matcher")}, indent=1))
    dest = ROOT / "benchmarks" / "results" / "bench_aster_scene.json"
    dest.write_text(strict_json(result, indent=1))
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
